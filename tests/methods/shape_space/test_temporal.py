"""Tests for service.methods.shape_space.temporal: sequence projection (eq. 5–6) and retiming (§6.2)."""

import itertools

import numpy as np
import pytest

from service.methods.shape_space.temporal import (
    extend_to_full_motion, monotonic_assignment, retime, sample_sequence, segment_projection,
    sequence_projection,
)


def smoothstep(x):
    return x * x * (3 - 2 * x)


def _eased(A, B, n, ease=smoothstep):
    s = ease(np.linspace(0, 1, n))
    return A + s[:, None] * (B - A)


def test_dp_finds_a_known_monotonic_mapping():
    rng = np.random.default_rng(0)
    beta = np.cumsum(rng.normal(size=(25, 12)), axis=0)           # a wandering curve, 25 frames
    tau = np.sort(rng.uniform(0, 24, 9))                          # known, increasing times
    alpha = sample_sequence(beta, tau) + rng.normal(scale=1e-3, size=(9, 12))
    proj = sequence_projection(alpha, beta)
    assert np.array_equal(proj.segment, np.minimum(np.floor(tau).astype(int), 23))
    np.testing.assert_allclose(proj.times, tau, atol=5e-3)
    assert np.all(np.diff(proj.segment) >= 0)


def test_dp_is_optimal_among_all_monotonic_assignments():
    rng = np.random.default_rng(1)
    for _ in range(20):
        E = rng.uniform(size=(4, 5))
        P, cost = monotonic_assignment(E)
        best = min(sum(E[i, p[i]] for i in range(4))
                   for p in itertools.combinations_with_replacement(range(5), 4))
        assert cost == pytest.approx(best) and np.all(np.diff(P) >= 0)
        assert sum(E[i, P[i]] for i in range(4)) == pytest.approx(cost)


def test_dp_respects_order_where_the_nearest_segment_would_not():
    # frame 1 is nearest to segment 0 but must not go before frame 0's segment 3
    E = np.array([[9.0, 9.0, 9.0, 0.0, 9.0],
                  [0.0, 9.0, 9.0, 1.0, 5.0]])
    P, cost = monotonic_assignment(E)
    assert P.tolist() == [3, 3] and cost == 1.0


def test_segment_projection_matches_dense_search():
    rng = np.random.default_rng(2)
    alpha, beta = rng.normal(size=(3, 5)), rng.normal(size=(6, 5))
    Om = rng.uniform(0.1, 2.0, 5)
    T, E = segment_projection(alpha, beta, Om)
    t = np.linspace(0, 1, 20001)
    for i in range(3):
        for j in range(5):
            pts = t[:, None] * beta[j] + (1 - t[:, None]) * beta[j + 1]
            d = np.sqrt((((alpha[i] - pts) ** 2) * Om).sum(1))
            assert T[i, j] == pytest.approx(t[np.argmin(d)], abs=1e-4)
            assert E[i, j] == pytest.approx(d.min(), abs=1e-8)


def test_retime_transfers_the_database_dynamics():
    rng = np.random.default_rng(3)
    A, B = rng.normal(size=10), rng.normal(size=10)
    beta = _eased(A, B, 40)                                        # ease-in/out in the database
    res = retime(A, B, [beta], length=12)
    s = np.linspace(0, 1, 12)
    # exact up to the piecewise-linear time curve through m samples (§6.2): 0.021 at the ends
    np.testing.assert_allclose(res.progress, smoothstep(s), atol=0.025)
    np.testing.assert_allclose(res.progress[2:-2], smoothstep(s)[2:-2], atol=0.003)
    assert res.progress[0] == 0 and res.progress[-1] == 1 and np.all(np.diff(res.progress) >= 0)
    assert res.span == pytest.approx((0.0, 39.0))
    # the keyframe blend i/(m-1) is shown at the time where the database reached it
    np.testing.assert_allclose(smoothstep(res.timestamps / 11), s, atol=0.01)


def test_retime_picks_the_matching_sequence_and_extends_to_the_full_motion():
    rng = np.random.default_rng(4)
    A, B, C = rng.normal(size=(3, 10))
    other = _eased(A, C, 30)                                       # a different motion
    smile = np.concatenate([_eased(A, B, 30), _eased(B, A, 20)[1:]])  # there and back
    mid = sample_sequence(smile, [15.0])[0]                        # halfway up the smile
    part = retime(A, mid, [other, smile], length=10)
    assert part.sequence == 1 and part.span == pytest.approx((0.0, 15.0), abs=1e-6)
    full = retime(A, mid, [other, smile], length=10, extend=True)
    assert full.span == pytest.approx((0.0, 29.0))                 # up to the peak, not back
    s = np.linspace(0, 1, 10)
    np.testing.assert_allclose(full.progress, smoothstep(s), atol=0.03)    # 0.025 at the ends
    np.testing.assert_allclose(full.progress[2:-2], smoothstep(s)[2:-2], atol=0.005)
    # the first half of a smoothstep accelerates: the retimed progress starts slower than linear
    assert np.all(part.progress[1:-1] < s[1:-1])
    assert extend_to_full_motion(smile, 0.0, 15.0) == pytest.approx((0.0, 29.0))


def test_retime_with_identical_keyframes_stays_linear():
    beta = _eased(np.zeros(4), np.ones(4), 10)
    res = retime(np.zeros(4) + 0.5, np.zeros(4) + 0.5, [beta], length=5)
    np.testing.assert_allclose(res.progress, np.linspace(0, 1, 5))
