"""Tests for service.methods.shape_space.markers: the marker shell, exact and soft."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.geometry.closest_point import surface_points
from service.geometry.thin_shell import complete_handles, shell_prior_scale, soft_handles
from service.methods.inputs import InvalidInput
from service.methods.shape_space.markers import MarkerShell


@pytest.fixture(scope="module")
def shell(rig_mesh):
    V, F = rig_mesh
    rng = np.random.default_rng(2)
    tri = rng.choice(len(F), 25, replace=False)
    bary = rng.dirichlet(np.ones(3), 25)
    return MarkerShell.build(V, F, tri, bary, np.ones(25))


def test_soft_marker_shell_is_the_map_solve_and_zero_noise_interpolates(shell):
    rng = np.random.default_rng(3)
    R = Rotation.from_euler("xyz", [3, -5, 2], degrees=True)
    local = shell.rest + rng.normal(0, 1.0, (4, shell.n_markers, 3))
    world = R.apply(local.reshape(-1, 3)).reshape(local.shape) + [5.0, -2.0, 1.0]
    world[2, [1, 6]] = np.nan
    tau = shell.prior_scale(world)
    # the database's τ: the prior scale of the head-aligned, exactly interpolated handles
    from service.geometry.rigid import rigid_align
    full = world[np.isfinite(world).all(axis=(1, 2))]
    u = np.stack([rigid_align(P, shell.rest, shell.weights).apply(P) - shell.rest for P in full])
    assert tau == pytest.approx(shell_prior_scale(shell.energy, u))
    exact = shell.with_marker_noise(0.0, None)
    soft = shell.with_marker_noise(0.3, tau)
    assert soft.noise_ratio == pytest.approx(0.09 / tau ** 2) and exact.noise_ratio == 0
    with pytest.raises(ValueError, match="prior"):
        shell.with_marker_noise(0.3, None)
    X_exact, X_soft = exact(world), soft(world)
    for f in range(4):
        T = rigid_align(world[f], shell.rest, shell.weights)
        vis = np.isfinite(world[f]).all(axis=1)
        m = np.where(vis[:, None], T.apply(world[f]) - shell.rest, np.nan)
        hard = T.inverse().apply(shell.neutral + shell.basis @ complete_handles(shell.energy, m))
        map_ = T.inverse().apply(shell.neutral + shell.basis @ soft_handles(shell.energy, m, soft.noise_ratio))
        np.testing.assert_allclose(X_exact[f], hard, atol=1e-8)
        np.testing.assert_allclose(X_soft[f], map_, atol=1e-8)
    assert np.abs(X_soft - X_exact).max() > 0.01
    with pytest.raises(InvalidInput, match="every marker"):
        shell.prior_scale(np.full((2, shell.n_markers, 3), np.nan))
