"""The performance flow graph's voting (fyffe §4.1) on constructed confidence tables."""

from __future__ import annotations

import numpy as np
import pytest

from service.errors import InvalidInput
from service.methods.tracking.graph import vote
from service.methods.tracking.params import TrackingParams


def test_vote_picks_the_best_scan_per_region_and_not_a_mediocre_one():
    # 3 scans × 2 regions × 1 frame: scan 0 best for region 0, scan 1 for region 1, scan 2
    # mediocre in both. By hand: pick (0, r0) = 0.9; subtract (0.9, 0.3): scan 1 → (−0.6,
    # 0.5), scan 2 → (−0.4, 0.2); pick (1, r1) = 0.5 ≥ 0.18; subtract (0.3, 0.8): scan 2 →
    # (−0.7, −0.6); everything < 0.18: stop.
    table = np.array([[[0.9], [0.3]], [[0.3], [0.8]], [[0.5], [0.5]]])
    assert vote(table, 0.04, 0.2) == [(0, 0), (1, 0)]


def test_vote_hat_suppresses_neighbouring_frames_by_the_slope():
    # one scan, one region, confidence 1 at each of 31 frames. By hand, slope 0.04: the
    # edge at 0 leaves 0.04·t up to t = 25 and 1 beyond; the edge at 25 (the first maximum)
    # then cancels everything in between exactly (0.04 t − (1 − 0.04 (25 − t)) = 0) and
    # leaves 0.2 at t = 30, below a 25 % threshold: two edges.
    table = np.ones((1, 1, 31))
    assert vote(table, 0.04, 0.25) == [(0, 0), (0, 25)]
    # slope 0.1 (hat 10 frames wide): an edge every 10 frames
    assert vote(table, 0.1, 0.25) == [(0, 0), (0, 10), (0, 20), (0, 30)]
    # a lower stop threshold keeps the 0.2 left at t = 30
    assert vote(table, 0.04, 0.15) == [(0, 0), (0, 25), (0, 30)]


def test_vote_ignores_missing_candidates_and_picks_each_pair_once():
    table = np.full((2, 3, 10), np.nan)
    table[1, :, 5] = [0.6, 0.7, 0.8]
    assert vote(table) == [(1, 5)]
    assert vote(np.full((1, 1, 4), np.nan)) == []


def test_tracking_params_refuse_out_of_range_values():
    assert TrackingParams().hat_slope == 0.04 and TrackingParams().stop_fraction == 0.2
    with pytest.raises(InvalidInput, match="stop_fraction"):
        TrackingParams(stop_fraction=1.5)
    with pytest.raises(InvalidInput, match="not a parameter"):
        TrackingParams(hat_slop=0.1)


def test_vote_adds_the_grounds_best_candidate_when_it_was_not_chosen():
    table = np.array([[[0.5, 0.6, 0.4]], [[0.9, 0.9, 0.9]]])     # scan 0 = ground, never best
    edges = vote(table, 0.04, 0.2, ground=0)
    assert (0, 1) in edges and edges[-1] == (0, 1)
    assert all(s == 1 for s, _ in edges[:-1])
