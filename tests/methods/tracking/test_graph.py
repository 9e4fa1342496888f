"""The performance flow graph's voting (fyffe §4.1) on constructed confidence tables."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.errors import InvalidInput
from service.methods.tracking.graph import consistency, vote
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


def test_vote_per_scan_suppression_leaves_other_scans_their_edges():
    # the mediocre-scan table: with "scan" suppression an edge only accounts for its own
    # scan's curves, so after (0, r0) = 0.9 and (1, r1) = 0.8 scan 2's 0.5 ≥ 0.18 is still
    # standing and is chosen too
    table = np.array([[[0.9], [0.3]], [[0.3], [0.8]], [[0.5], [0.5]]])
    assert vote(table, 0.04, 0.2, suppression="scan") == [(0, 0), (1, 0), (2, 0)]
    # two scans, confidence 1 at each of 31 frames, slope 0.04, stop 0.25: per scan the
    # hat leaves 0.04·t up to t = 25 (by hand as in the test above), so each scan gets
    # frames 0 and 25 (ties go to the first in (scan, region, frame) order); with "all"
    # scan 0's edges satisfy scan 1 as well
    table = np.ones((2, 1, 31))
    assert vote(table, 0.04, 0.25, suppression="scan") == [(0, 0), (0, 25), (1, 0), (1, 25)]
    assert vote(table, 0.04, 0.25, suppression="all") == [(0, 0), (0, 25)]
    with pytest.raises(ValueError, match="suppression"):
        vote(table, suppression="some")
    with pytest.raises(InvalidInput, match="vote_suppression"):
        TrackingParams(vote_suppression="some")


def test_consistency_is_one_for_inverse_flows_and_falls_with_the_round_trip_miss():
    H, W = 40, 50
    shift = np.array([2.0, 1.0], np.float32)
    f = np.broadcast_to(shift, (H, W, 2)).copy()
    inner = (slice(5, -5), slice(5, -5))
    # b = −f: the round trip returns to the start everywhere
    np.testing.assert_allclose(consistency(f, -f, 0.5, 0.0)[inner], 1.0, atol=1e-6)
    # b = 0: every pixel misses by |f| = √5 px → exp(−(√5/σ)²)
    zero = np.zeros_like(f)
    np.testing.assert_allclose(consistency(f, zero, 2.0, 0.0)[inner], np.exp(-5.0 / 4.0), rtol=1e-5)
    # b = −f + 0.3 px: a miss of 0.3 px → exp(−0.36) at σ = 0.5; smoothing keeps a constant
    near = -f + np.array([0.3, 0.0], np.float32)
    np.testing.assert_allclose(consistency(f, near, 0.5, 3.0)[inner], np.exp(-0.36), rtol=1e-4)
    # σ = 0 switches the weight off
    assert np.all(consistency(f, zero, 0.0, 3.0) == 1.0)


def test_edge_flows_confidence_drops_where_the_two_directions_disagree():
    # a textured image and a copy shifted by 2 px: both flows agree, the confidence is the
    # NCC's; an unrelated target: the flows disagree and the consistency takes it down
    from service.methods.tracking.graph import edge_flows
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (64, 64)).astype(np.float32), (0, 0), 1.5)
    base = cv2.normalize(base, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
    moved = np.roll(base, 2, axis=1)
    other = cv2.GaussianBlur(rng.uniform(0, 255, (64, 64)).astype(np.float32), (0, 0), 1.5)
    other = cv2.normalize(other, None, 20, 235, cv2.NORM_MINMAX).astype(np.uint8)
    inner = (slice(12, -12), slice(12, -12))
    on = TrackingParams()
    off = TrackingParams(consistency_sigma=0.0)
    good = edge_flows(base[None], moved[None], ("scan", 0), ("frame", 0), on)
    good_off = edge_flows(base[None], moved[None], ("scan", 0), ("frame", 0), off)
    np.testing.assert_allclose(good.forward[0].flow[inner], np.broadcast_to([2.0, 0.0], (40, 40, 2)), atol=0.1)
    assert good.forward[0].confidence[inner].mean() > 0.9 * good_off.forward[0].confidence[inner].mean()
    assert good.forward[0].confidence[inner].mean() > 0.8
    bad = edge_flows(base[None], other[None], ("scan", 0), ("frame", 0), on)
    bad_off = edge_flows(base[None], other[None], ("scan", 0), ("frame", 0), off)
    assert bad.forward[0].confidence[inner].mean() <= bad_off.forward[0].confidence[inner].mean()
    assert bad.forward[0].confidence[inner].mean() < 0.1
