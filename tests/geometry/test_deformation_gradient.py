"""Tests for service.geometry.deformation_gradient: gradients, polar/log encoding, Poisson."""

from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from service.geometry.deformation_gradient import (
    GradientOperator,
    PoissonReconstruction,
    boundary_laplacian_1d,
    boundary_vertex_indices,
    decode,
    deformation_gradients,
    encode,
    poisson_reconstruct,
    polar_decomposition,
    rotation_exp,
    rotation_log,
)
from service.geometry.laplacian import cotangent_laplacian

RIG = Path(__file__).resolve().parents[2] / "service" / "samples" / "data" / "ict_face_rig.npz"


def random_rotations(rng: np.random.Generator, k: int) -> np.ndarray:
    q = rng.standard_normal((k, 4))
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)


@pytest.fixture(scope="module")
def rig():
    d = np.load(RIG)
    V = d["neutral"].astype(np.float64)
    names = list(d["expression_names"])
    V1 = (V + d["expression_deltas"][names.index("jawOpen")]
          + 0.8 * d["expression_deltas"][names.index("mouthSmile_L")]
          + d["expression_deltas"][names.index("browInnerUp_L")])
    return V, V1.astype(np.float64), d["triangles"].astype(np.int64)


def test_deformation_gradients_of_rigid_motion_are_pure_rotations(rig):
    V, _, F = rig
    R = random_rotations(np.random.default_rng(5), 1)[0]
    t = np.array([10.0, -250.0, 33.0])
    G = deformation_gradients(V, V @ R.T + t, F)
    assert G.shape == (len(F), 3, 3)
    np.testing.assert_allclose(G, np.broadcast_to(R, G.shape), rtol=0, atol=1e-10)
    Rp, S = polar_decomposition(G)
    np.testing.assert_allclose(Rp, np.broadcast_to(R, G.shape), rtol=0, atol=1e-10)
    np.testing.assert_allclose(S, np.broadcast_to(np.eye(3), G.shape), rtol=0, atol=1e-10)


def test_deformation_gradients_map_rest_edges_and_scaled_normals(rig):
    V, V1, F = rig
    G = deformation_gradients(V, V1, F)
    e0 = V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    e1 = V1[F[:, 1]] - V1[F[:, 0]], V1[F[:, 2]] - V1[F[:, 0]]
    for a, b in zip(e0, e1):
        np.testing.assert_allclose(np.einsum("fij,fj->fi", G, a), b, rtol=0, atol=1e-11)
    # Sumner & Popović's fourth vertex: n / sqrt(|n|) maps to the deformed n' / sqrt(|n'|)
    n0, n1 = np.cross(*e0), np.cross(*e1)
    n0 /= np.sqrt(np.linalg.norm(n0, axis=1, keepdims=True))
    n1 /= np.sqrt(np.linalg.norm(n1, axis=1, keepdims=True))
    np.testing.assert_allclose(np.einsum("fij,fj->fi", G, n0), n1, rtol=0, atol=1e-11)
    # batched frames give the same per-frame answer
    Gb = deformation_gradients(V, np.stack([V1, V]), F)
    assert Gb.shape == (2, len(F), 3, 3)
    np.testing.assert_allclose(Gb[0], G, rtol=0, atol=1e-13)
    np.testing.assert_allclose(Gb[1], np.broadcast_to(np.eye(3), G.shape), rtol=0, atol=1e-12)


def test_polar_decomposition_reconstructs_and_s_is_symmetric_positive():
    rng = np.random.default_rng(11)
    G = np.eye(3) + 0.4 * rng.standard_normal((500, 3, 3))
    G = G[np.linalg.det(G) > 0]
    R, S = polar_decomposition(G)
    np.testing.assert_allclose(R @ S, G, rtol=0, atol=1e-12)
    np.testing.assert_allclose(S, np.swapaxes(S, 1, 2), rtol=0, atol=0)
    assert np.linalg.eigvalsh(S).min() > 0
    np.testing.assert_allclose(np.linalg.det(R), 1.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               rtol=0, atol=1e-12)
    # a reflection still gives a proper rotation; the sign goes into S
    M = np.diag([1.0, 1.0, -1.0]) @ G[0]
    Rm, Sm = polar_decomposition(M)
    assert abs(np.linalg.det(Rm) - 1.0) < 1e-12
    np.testing.assert_allclose(Rm @ Sm, M, rtol=0, atol=1e-12)
    assert (np.linalg.eigvalsh(Sm) < 0).sum() == 1


def test_rotation_exp_known_values():
    np.testing.assert_allclose(rotation_exp(np.array([0.0, 0.0, np.pi / 2])),
                               [[0, -1, 0], [1, 0, 0], [0, 0, 1]], rtol=0, atol=1e-15)
    np.testing.assert_allclose(rotation_exp(np.array([np.pi, 0.0, 0.0])),
                               np.diag([1.0, -1.0, -1.0]), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(rotation_exp(np.zeros((2, 3))),
                                  np.broadcast_to(np.eye(3), (2, 3, 3)))
    w = np.array([1e-9, -2e-9, 3e-9])
    np.testing.assert_allclose(rotation_exp(w), np.eye(3) + np.array(
        [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]), rtol=0, atol=1e-17)


def test_rotation_exp_of_log_is_identity_incl_near_zero_and_pi():
    rng = np.random.default_rng(2)
    axes = rng.standard_normal((6, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.array([0.0, 1e-12, 1e-7, 1e-4, 0.3, 2.0, np.pi - 1e-3, np.pi - 1e-6,
                       np.pi - 1e-9, np.pi])
    W = (axes[:, None, :] * angles[None, :, None]).reshape(-1, 3)
    R = np.concatenate([rotation_exp(W), random_rotations(rng, 200), [np.diag([-1.0, -1.0, 1.0])]])
    w = rotation_log(R)
    np.testing.assert_allclose(rotation_exp(w), R, rtol=0, atol=1e-12)
    assert np.linalg.norm(w, axis=1).max() <= np.pi + 1e-12
    # log(exp(w)) == w strictly inside the ball of radius π
    inside = np.linalg.norm(W, axis=1) < np.pi - 1e-5
    np.testing.assert_allclose(rotation_log(rotation_exp(W[inside])), W[inside], rtol=0, atol=1e-10)


def test_encode_decode_round_trip():
    rng = np.random.default_rng(4)
    G = np.eye(3) + 0.3 * rng.standard_normal((100, 3, 3))
    G = G[np.linalg.det(G) > 0]
    w, s = encode(G)
    assert w.shape == (len(G), 3) and s.shape == (len(G), 6)
    np.testing.assert_allclose(decode(w, s), G, rtol=0, atol=1e-12)


def test_gradient_operator_is_consistent_with_the_cotangent_laplacian(rig):
    V, V1, F = rig
    op = GradientOperator(V, F)
    assert op.D.shape == (3 * len(F), len(V))
    # Dᵀ diag(A) D == -L  (the Dirichlet energy of piecewise-linear fields)
    K = op.D.T @ sp.diags(np.repeat(op.areas, 3)) @ op.D
    diff = (K + cotangent_laplacian(V, F)).tocoo()
    assert np.abs(diff.data).max() < 1e-12
    # the gradient of a linear function is its (tangential) coefficient vector
    a = np.array([0.3, -1.2, 2.0])
    g = op.D @ (V @ a)
    Nn = op.normals
    np.testing.assert_allclose(g.reshape(-1, 3), a - (Nn @ a)[:, None] * Nn, rtol=0, atol=1e-10)
    # the Jacobian of the deformed positions is G projected on the rest tangent plane
    G = deformation_gradients(V, V1, F)
    J = op.jacobian(V1)
    np.testing.assert_allclose(J, G - (G @ Nn[:, :, None]) * Nn[:, None, :], rtol=0, atol=1e-10)
    np.testing.assert_allclose(op.target_gradients(G), op.D @ V1, rtol=0, atol=1e-10)


def test_poisson_reconstruction_recovers_deformed_mesh_up_to_translation(rig):
    V, V1, F = rig
    G = deformation_gradients(V, V1, F)
    rec = PoissonReconstruction(V, F)
    X = rec.solve(G)
    shift = (X - V1).mean(axis=0)
    scale = np.abs(V1).max()
    assert np.abs(X - shift - V1).max() < 1e-8 * scale
    # the pin (vertex 0, one connected component) stays at its rest position by default
    np.testing.assert_array_equal(rec.pinned, [0])
    np.testing.assert_array_equal(X[0], V[0])
    # pinned where asked: then it is V1 exactly
    X2 = rec.solve(G, pinned_positions=V1[rec.pinned])
    assert np.abs(X2 - V1).max() < 1e-8 * scale
    # batched frames with one factorization
    Xb = rec(np.stack([G, deformation_gradients(V, V, F)]))
    np.testing.assert_allclose(Xb[0], X, rtol=0, atol=1e-12)
    assert np.abs(Xb[1] - V).max() < 1e-8 * scale


def test_poisson_boundary_term_is_exact_for_consistent_reference_and_pulls_toward_it(rig):
    V, V1, F = rig
    G = deformation_gradients(V, V1, F)
    rec = PoissonReconstruction(V, F, boundary_weight=0.05)
    X = rec.solve(G, pinned_positions=V1[rec.pinned], boundary_reference=V1)
    assert np.abs(X - V1).max() < 1e-8 * np.abs(V1).max()
    # a reference whose boundary differs from the targets' (the rest mesh): the boundary's
    # 1D Laplacian moves toward the reference's monotonically with the weight
    Lb = boundary_laplacian_1d(F, len(V))
    target = np.linalg.norm(Lb @ V - Lb @ V1)
    errs = []
    for w in (0.0, 0.05, 1.0, 100.0):
        X = poisson_reconstruct(V, F, G, boundary_weight=w, boundary_reference=V)
        errs.append(np.linalg.norm(Lb @ X - Lb @ V))
    assert errs[0] == pytest.approx(target, rel=1e-8)
    assert errs[0] > errs[1] > errs[2] > errs[3]
    # a second-derivative term against a first-derivative energy: at the paper's w = 0.05
    # it is gentle (measured 1.5 % for this pure conflict), at w = 100 it halves the mismatch
    assert errs[3] < 0.6 * errs[0]


def test_poisson_batch_is_one_solve_equal_bit_for_bit_to_its_frames(rig):
    """A batch (B,m,3,3) is one solve with 3B right-hand sides (bermano2014 §5.5 per frame of
    an /enhance request): each frame's result is exactly that of solving it alone, with
    per-frame and shared boundary references and pinned positions."""
    V, V1, F = rig
    rng = np.random.default_rng(3)
    frames = np.stack([V1, V, V1 + 0.3 * rng.standard_normal(V1.shape), V1[::-1][np.argsort(np.arange(len(V))[::-1])]])
    G = deformation_gradients(V, frames, F)
    rec = PoissonReconstruction(V, F, boundary_weight=0.05)
    pins = frames[:, rec.pinned]
    batch = rec.solve(G, pinned_positions=pins, boundary_reference=frames)
    shared = rec.solve(G, boundary_reference=V1)
    for b in range(len(G)):
        np.testing.assert_array_equal(batch[b], rec.solve(G[b], pinned_positions=pins[b],
                                                          boundary_reference=frames[b]))
        np.testing.assert_array_equal(shared[b], rec.solve(G[b], boundary_reference=V1))
    assert batch.shape == frames.shape and batch.flags.c_contiguous


def test_boundary_laplacian_1d_of_a_square_loop():
    # a 3x3 grid of vertices (2x2 quads, 8 triangles): 8 boundary vertices, centre interior
    x, y = np.meshgrid(np.arange(3.0), np.arange(3.0))
    V = np.c_[x.ravel(), y.ravel(), np.zeros(9)]
    idx = np.arange(9).reshape(3, 3)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    np.testing.assert_array_equal(boundary_vertex_indices(F), [0, 1, 2, 3, 5, 6, 7, 8])
    Lb = boundary_laplacian_1d(F, 9)
    assert Lb.shape == (8, 9)
    d = Lb @ V
    # edge midpoints are straight (0), corners point inward by (±½, ±½)
    np.testing.assert_allclose(d[[1, 3, 4, 6]], 0.0, atol=1e-15)
    np.testing.assert_allclose(d[0], [-0.5, -0.5, 0.0])
    np.testing.assert_allclose(d[7], [0.5, 0.5, 0.0])


def test_polar_newton_matches_the_svd_factors_including_ill_conditioned_and_mixed_signs():
    from service.geometry.deformation_gradient import _polar_svd

    rng = np.random.default_rng(12)
    G = np.eye(3) + 0.4 * rng.standard_normal((400, 3, 3))
    # ill-conditioned (singular values 1e-5 .. 10) and scaled stretches
    U, _, Vt = np.linalg.svd(rng.standard_normal((100, 3, 3)))
    U[np.linalg.det(U) < 0, :, 2] *= -1
    Vt[np.linalg.det(Vt) < 0, 2] *= -1
    sig = 10.0 ** rng.uniform(-5, 1, (100, 3))
    G = np.concatenate([G, U @ (sig[..., None] * Vt)])
    R, S = polar_decomposition(G.reshape(50, 10, 3, 3))          # any leading shape
    R, S = R.reshape(-1, 3, 3), S.reshape(-1, 3, 3)
    Rs, Ss = _polar_svd(G.copy())
    np.testing.assert_allclose(R, Rs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(S, 0.5 * (Ss + np.swapaxes(Ss, 1, 2)), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, rtol=0, atol=1e-12)


def test_inverse3_matches_lapack():
    from service.geometry.deformation_gradient import inverse3

    X = np.random.default_rng(13).standard_normal((2, 50, 3, 3))
    np.testing.assert_allclose(inverse3(X) @ X, np.broadcast_to(np.eye(3), X.shape), rtol=0, atol=1e-9)
    np.testing.assert_allclose(inverse3(X), np.linalg.inv(X), rtol=1e-9, atol=1e-12)
