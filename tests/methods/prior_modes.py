"""A check every marker-driven kind's tests share: its ``marker_modes`` (the modes a job's
``marker_filter_frames: "auto"`` filters in) are its learned prior's eigenvectors, by
decreasing variance, about its rest markers."""

from __future__ import annotations

import numpy as np


def check_marker_modes(modes, rest: np.ndarray, prior, weights: np.ndarray) -> None:
    """``modes`` (:class:`~service.geometry.marker_filter.MarkerModes`) diagonalize the
    ``prior``'s covariance with decreasing eigenvalues, with orthonormal columns, about
    ``rest`` (M,3) aligned with ``weights`` (M,)."""
    np.testing.assert_array_equal(modes.rest, rest)
    np.testing.assert_array_equal(modes.weights, weights)
    U = modes.vectors
    np.testing.assert_allclose(U.T @ U, np.eye(len(U)), atol=1e-10)
    D = U.T @ prior.covariance @ U
    scale = np.abs(D).max()
    np.testing.assert_allclose(D, np.diag(np.diag(D)), atol=1e-9 * scale)
    assert (np.diff(np.diag(D)) <= 1e-9 * scale).all()
