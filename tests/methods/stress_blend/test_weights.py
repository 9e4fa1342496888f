import numpy as np

from service.methods.stress_blend.weights import shepard_weights


def _scans(seed=0, S=5, n=40):
    return np.random.default_rng(seed).normal(scale=0.1, size=(S, n, 3))


def test_partition_of_unity_and_non_negative():
    scans = _scans()
    s = np.random.default_rng(1).normal(scale=0.1, size=(3, 40, 3))
    w = shepard_weights(s, scans)
    assert w.shape == (3, 40, 5)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=-1), 1.0, atol=1e-14)


def test_frame_equal_to_a_scan_is_one_hot_exactly():
    scans = _scans()
    for k in range(5):
        w = shepard_weights(scans[k], scans)
        expected = np.zeros((40, 5))
        expected[:, k] = 1.0
        np.testing.assert_array_equal(w, expected)


def test_hand_computed_two_scans_and_smooth_near_a_scan():
    # 1D: scans at 0 and 1 (p = 2): w_1(x) = x² / (x² + (1 − x)²)
    scans = np.zeros((2, 1, 3))
    scans[1, 0, 0] = 1.0
    for x in (0.25, 0.5, 0.9):
        w = shepard_weights(np.array([[x, 0.0, 0.0]]), scans, global_weight=0.0)
        np.testing.assert_allclose(w[0, 1], x * x / (x * x + (1 - x) ** 2), rtol=1e-14)
    # near scan 0 the weight of scan 1 grows like ε² (zero slope: differentiable at the scan)
    e = np.array([1e-3, 2e-3])
    w1 = shepard_weights(np.column_stack([e, 0 * e, 0 * e])[:, None, :], scans, global_weight=0.0)[:, 0, 1]
    np.testing.assert_allclose(w1[1] / w1[0], 4.0, rtol=1e-2)


def test_coincident_scans_split_equally_without_the_global_term():
    scans = np.zeros((3, 2, 3))
    scans[2, :, 1] = 0.5
    w = shepard_weights(np.zeros((2, 3)), scans, global_weight=0.0)   # scans 0, 1 coincide with the frame
    np.testing.assert_allclose(w, [[0.5, 0.5, 0.0]] * 2)


def test_global_term_breaks_local_ties_and_keeps_scans_exact():
    # scans 0 and 1 agree at vertex 0 but differ at vertex 1: at a frame equal to scan 1,
    # the local term alone splits vertex 0; with β > 0 vertex 0 follows the whole frame
    scans = np.zeros((2, 2, 3))
    scans[1, 1, 0] = 0.3
    local = shepard_weights(scans[1], scans, global_weight=0.0)
    np.testing.assert_allclose(local, [[0.5, 0.5], [0.0, 1.0]])
    w = shepard_weights(scans[1], scans, global_weight=0.5)
    np.testing.assert_array_equal(w, [[0.0, 1.0], [0.0, 1.0]])
    # hand-computed off the scans: frame s = (0.1 at vertex 1): local d² = (0, 0.01) to scan 0,
    # (0, 0.04) to scan 1; D² = 0.005, 0.02; β = 0.5 → d² at vertex 0 = 0.00125, 0.005
    s = np.zeros((2, 3))
    s[1, 0] = 0.1
    w = shepard_weights(s, scans, global_weight=0.5)
    np.testing.assert_allclose(w[0, 1], 0.00125 / (0.00125 + 0.005), rtol=1e-12)
    np.testing.assert_allclose(w[1, 1], 0.01125 / (0.01125 + 0.045), rtol=1e-12)
