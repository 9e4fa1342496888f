"""Temporal filtering of marker trajectories over a whole performance, robust to occlusion.

Optical mocap markers carry per-frame noise (σ ≈ 0.1–0.5 mm, independent from frame to
frame) on a motion that is smooth at the capture rate. Over a clip (a synthesis job, not a
single real-time frame, which has no future) each coordinate of each marker is replaced
by a **Gaussian-weighted local polynomial fit** (a Savitzky–Golay filter with Gaussian
weights, i.e. local polynomial regression / LOESS without the robustness iterations):

    x̂(t) = a₀,   (a₀, a₁, …) = argmin Σ_τ g(τ) m(t+τ) (x(t+τ) − Σ_k a_k τ^k)²,
    g(τ) = exp(−τ² / 2s²),  |τ| ≤ ⌈3s⌉ frames,

with m the visibility mask (1 visible, 0 occluded). Written as moments of the masked
signal, ``Σ g τ^k m`` and ``Σ g τ^k m x``, it is a few 1-D correlations along time and one
small solve per sample, vectorized over markers and coordinates.

Why this form (and not a plain Gaussian blur or a Kalman/RTS smoother):

* degree ≥ 1 has no lag and no shrinkage on linear motion, at the clip's ends too, where
  a plain normalized Gaussian pulls a moving marker towards its interior mean; degree 2
  (the default) also keeps the peaks of accelerating motion (an expression's apex) that
  degree 0 or 1 flattens by ``s² x''/2``;
* occluded samples simply have weight 0. An occluded sample is filled only inside a short
  gap (a visible sample at most ``max_gap`` frames before *and* after it, default ⌈s⌉),
  where the fit interpolates; in a longer gap, and wherever the window holds fewer than
  ``min_support`` visible samples, it stays NaN, so the spatial completion of the thin
  shell (:func:`~service.geometry.thin_shell.soft_handles`) handles it instead of a
  polynomial extrapolating (a quadratic 3 frames into a gap is off by millimetres);
* an RTS smoother with a constant-acceleration model is the same linear smoother up to the
  shape of its kernel, but needs a process-noise level per marker; the window ``s`` is the
  one knob here.

Rigid head motion is not smooth at the frame rate in every capture (family b of the sample
actors shakes its head by ~1 mm from frame to frame, and a 2-frame window on its world
markers moved the surface by 1.3 mm). :func:`filter_performance` therefore filters the
markers in a head-aligned frame, as every method measures deformation (DESIGN.md: rigid
motion removed first), and puts each frame's own pose back: the per-frame rigid fit of
~100 markers is far less noisy than one marker.

Noise reduction for white noise: the variance falls by ``Σ h(τ)²`` with h the equivalent
kernel; for degree 2 the noise std falls to 0.69, 0.50, 0.41, 0.35 × for s = 1, 2, 3, 4 frames
(measured on white noise; the test pins s = 2 in ``tests/geometry/test_marker_filter.py``).
On the held-out performances of both sample families (30 fps, σ = 0.3 mm,
``benchmarks/marker_denoise.py``) s = 3 frames cut the noise reaching the thin shell from
0.40 to 0.17 mm (family a) and costs clean markers under 2 %; s = 6 already blurs the
motion (clean +28 %).

One window for a whole take is a compromise: a marker at rest wants the widest, an
expression's onset a narrow one or none, and clean markers none at all. ``"auto"``
(:func:`filter_markers_auto`) estimates the take's noise (:func:`~service.geometry.marker_prior.temporal_noise`)
and chooses the window per marker and frame by Stein's unbiased risk estimate, summed over
:data:`RISK_WINDOW_FRAMES` around each frame. World markers of the held-out performances
(level 0, σ = 0.3 mm, 3-D RMS error against the clean markers, mm, noisy / clean input;
in range, combinations, amplified):

| family | raw | s = 2 | s = 3 | s = 4 | auto |
|---|---|---|---|---|---|
| a | 0.519 / 0 | 0.268 / 0.009, 0.269 / 0.018, 0.268 / 0.029 | 0.226 / 0.028, 0.231 / 0.055, 0.241 / 0.090 | 0.208 / 0.064, 0.233 / 0.122, 0.287 / 0.206 | **0.204 / 0.003, 0.224 / 0.005, 0.230 / 0.005** |
| b | 0.518 / 0 | 0.271 / 0.016, 0.269 / 0.018, 0.271 / 0.045 | 0.233 / 0.051, 0.234 / 0.060, 0.268 / 0.143 | 0.229 / 0.108, 0.244 / 0.138, 0.366 / 0.305 | **0.214 / 0.002, 0.224 / 0.004, 0.245 / 0.005** |

The risk window was chosen on family a (σ_w ∈ {3, 6, 10, 15, 20, 30} frames: noisy error
falls to 15 and is flat beyond, 0.2190 mm mean at 15, 0.2188 at 20, 0.2192 at 30; clean
0.003–0.005 throughout) and confirmed on family b (6: 0.231, 15: 0.228, 30: 0.231); windows
beyond 8 frames were never chosen on family a (12 and 16 added: the same errors).

**In the modes of the model's marker prior.** A fixed window is the same linear filter on
every coordinate, so it commutes with any orthonormal change of basis; ``"auto"``'s choice
does not. Per marker coordinate it must keep the window an expression's onset allows, and
the noise of the directions the face never moves in passes with it. Given a marker-driven
model's learned prior (:class:`MarkerModes`: its eigenvectors, by decreasing variance, in
the model's head-aligned frame), :func:`filter_performance` chooses the window per prior
*mode* instead (:func:`filter_modes`): the few modes carrying the expression take narrow
windows where they move fast, and the many the training barely moves — almost pure noise
— take the widest. White noise stays white in an orthonormal basis, so the risk estimate
holds as it is; the basis comes from the training clips, not from the noisy take (a PCA of
the take itself is fitted to its noise and does worse than per coordinate: 0.20 against
0.135 mm on family a, both aligned with the true head pose).
The frames are aligned with the model's head-alignment weights, as its prior's were
(unweighted, the rigid fit absorbs part of a large expression, which no mode then holds:
family b amplified 0.133 → 0.131 instead of 0.118). Frames with an occluded marker keep
the per-coordinate fit. Measured on the held-out performances (level 0, σ = 0.3 mm; the
PDM's prior, fitted on the training clips; what reaches the thin shell after the model's
own head alignment and per-frame MAP at its σ̂ (``marker_noise_mm: "auto"``): the face's
mean vertex distance to the shell of the clean markers, mm, mean over in range /
combinations / amplified; ``benchmarks/marker_denoise.py --auto-filter``):

| family | per coordinate | per mode, :data:`AUTO_BANDWIDTHS` | per mode, :data:`MODE_BANDWIDTHS` |
|---|---|---|---|
| a, noisy / clean / occluded | 0.148 / 0.0096 / 0.0256 | 0.130 / 0.0093 / 0.0254 | **0.127** / 0.0093 / 0.0254 |
| b, noisy / clean / occluded | 0.137 / 0.0033 / 0.0297 | 0.123 / 0.0029 / 0.0291 | **0.121** / 0.0029 / 0.0291 |

(the wider windows chosen on a, confirmed on b). How far any choice among these windows
could go: each chosen by its true error instead of SURE (``truth=``, an oracle with the
same candidates and risk window; the table's ``per mode, oracle windows`` row) gives noisy
a 0.120 and b 0.116 (b amplified 0.118 → 0.112); windows of 32–64 frames added to
:data:`MODE_BANDWIDTHS` 0.127 → 0.126 on a (not kept). The filter costs 0.3–0.4 s per take
(the held-out ones: 146–154 frames, 118–150 markers; 0.2–0.3 s with occluded markers, whose
frames also take the per-coordinate pass) instead of 0.15–0.3 s per coordinate.

One consequence downstream: :func:`~service.geometry.marker_prior.frame_noise` reads σ̂ in
the prior's floor directions, which this filter smooths the most, so after it a noisy
take's σ̂ is 0.05–0.11 mm (family a; 0.12–0.13 per coordinate, clean takes 0.006–0.06)
while the noise left sits in the modes carrying the expression: the methods' MAP shrinks
less, and σ̂ no longer shows the take's noise, so a synthesis job passes the take as
captured for the reported confidence to read (:mod:`service.methods.confidence`, *Filtered
takes*). A MAP given the residual noise this filter leaves per mode and frame
(σ² Σ_τ w(τ)² of the chosen fit's equivalent kernel w) instead of σ̂² I was measured and not
kept: what reaches the shell falls 0.127 → 0.124 mm (a) and 0.121 → 0.119 (b), no more
with each take's true residual per mode (0.125 / 0.120); the expression modes' prior
variance is far above that noise, so their Wiener gain stays near 1 whatever it is. Nor
kept: the floor directions' part taken from the per-coordinate fit instead (so σ̂ reads
0.10–0.13 mm again on a noisy take), which gives back about half the gain (a 0.137, b
0.126 mm in the table's terms).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.geometry.marker_prior import AUTO, MarkerPrior, PriorEigen, temporal_noise
from service.geometry.rigid import MIN_POINTS, rigid_align

#: default window of the temporal filter, frames (σ of the Gaussian weights)
SIGMA_FRAMES = 2.0
#: default local polynomial degree
DEGREE = 2
#: the windows ``"auto"`` chooses among, frames (0: the sample itself)
AUTO_BANDWIDTHS = (0.0, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)
#: the windows ``"auto"`` chooses among in the prior's modes (:func:`filter_modes`): wider
#: too, for the modes that hold almost only noise (chosen on family a, confirmed on b)
MODE_BANDWIDTHS = AUTO_BANDWIDTHS + (12.0, 16.0, 24.0)
#: σ of the Gaussian over which ``"auto"`` sums each window's risk estimate, frames
#: (chosen on family a, confirmed on b: the module docstring)
RISK_WINDOW_FRAMES = 15.0
#: largest window a caller may ask for, frames (beyond, the filter blurs expressions away)
MAX_SIGMA_FRAMES = 30.0


def _moments(x: np.ndarray, kernels: np.ndarray) -> np.ndarray:
    """Σ_τ k_j(τ) x(t+τ) along axis 0 for each kernel row j: (J, *x.shape)."""
    from scipy.ndimage import correlate1d  # imported here: serve's start never needs it (issue 23)

    return np.stack([correlate1d(x, k, axis=0, mode="constant", cval=0.0) for k in kernels])


def _as_markers(markers: np.ndarray) -> np.ndarray:
    """``markers`` as float64 (F,M,3), or a ValueError naming the shape."""
    x = np.asarray(markers, dtype=np.float64)
    if x.ndim != 3 or x.shape[-1] != 3:
        raise ValueError(f"markers must be (frames, markers, 3), got {x.shape}")
    return x


def _gaussian(sigma_frames: float) -> np.ndarray:
    """exp(−τ²/2s²) over |τ| ≤ ⌈3s⌉ frames."""
    r = int(np.ceil(3 * sigma_frames))
    tau = np.arange(-r, r + 1, dtype=np.float64)
    return np.exp(-0.5 * (tau / sigma_frames) ** 2)


def _gap_distances(visible: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames since the previous and until the next visible sample (F,M) (0 if visible; a
    large number where there is none)."""
    F = len(visible)
    t = np.arange(F)[:, None]
    big = 10 * F + 10
    prev = np.maximum.accumulate(np.where(visible, t, -big), axis=0)
    nxt = np.minimum.accumulate(np.where(visible, t, 2 * big)[::-1], axis=0)[::-1]
    return t - prev, nxt - t


def _local_fit(x: np.ndarray, sigma_frames: float, degree: int, min_support: int | None,
               max_gap: int | None) -> tuple[np.ndarray, np.ndarray]:
    """The local polynomial fit x̂ (F,M,3) and its hat values h (F,M) = ∂x̂(t)/∂x(t), the
    weight of each sample in its own estimate ((A⁻¹)₀₀: only τ = 0 puts x(t) in the
    moments, with g(0) = 1); both NaN where the fit is undefined (:func:`filter_markers`)."""
    min_support = degree + 2 if min_support is None else int(min_support)
    g = _gaussian(sigma_frames)
    r = len(g) // 2
    tau = np.arange(-r, r + 1, dtype=np.float64)
    visible = np.isfinite(x).all(axis=2).astype(np.float64)              # (F,M)
    xv = np.where(visible[..., None] > 0, x, 0.0)
    p = degree + 1
    # normal matrix entries Σ g τ^(i+j) m and right-hand sides Σ g τ^i m x
    A_m = _moments(visible, g * tau[None, :] ** np.arange(2 * p - 1)[:, None])   # (2p-1,F,M)
    b_m = _moments(xv, g * tau[None, :] ** np.arange(p)[:, None])                # (p,F,M,3)
    idx = np.add.outer(np.arange(p), np.arange(p))
    A = np.moveaxis(A_m[idx], (0, 1), (-2, -1))                                  # (F,M,p,p)
    b = np.moveaxis(b_m, 0, -2)                                                  # (F,M,p,3)
    count = _moments(visible, (np.abs(tau) <= r).astype(np.float64)[None])[0]
    # scale τ by s so the normal matrix is well conditioned for any window
    s = sigma_frames ** np.arange(p)
    A = A / np.multiply.outer(s, s)
    b = b / s[:, None]
    ok = count >= min_support
    before, after = _gap_distances(visible > 0)
    reach = int(np.ceil(sigma_frames)) if max_gap is None else int(max_gap)
    ok &= (visible > 0) | ((before <= reach) & (after <= reach))
    cond_ok = np.zeros_like(ok)
    cond_ok[ok] = np.linalg.cond(A[ok]) < 1e8
    ok &= cond_ok
    out = np.full_like(x, np.nan)
    hat = np.full(x.shape[:2], np.nan)
    if ok.any():
        e0 = np.zeros((p, 1))
        e0[0] = 1.0
        rhs = np.concatenate([b[ok], np.broadcast_to(e0, (int(ok.sum()), p, 1))], axis=-1)
        sol = np.linalg.solve(A[ok], rhs)[:, 0, :]                             # (k,4)
        out[ok] = sol[:, :3]
        hat[ok] = sol[:, 3]
    return out, hat


def filter_markers(markers: np.ndarray, sigma_frames: float | str = SIGMA_FRAMES, degree: int = DEGREE,
                   min_support: int | None = None, max_gap: int | None = None) -> np.ndarray:
    """Marker trajectories smoothed in time by a Gaussian-weighted local polynomial fit.

    Parameters
    ----------
    markers : (F,M,3) float   marker positions per frame, mm (any unit); NaN rows occluded
    sigma_frames : float      s > 0, the Gaussian weights' σ in frames (0: no filtering);
                              ``"auto"``: chosen per marker and frame, :func:`filter_markers_auto`
    degree : int              local polynomial degree, 0 … 3
    min_support : int         visible samples a window needs (default ``degree + 2``); a
                              sample with less stays NaN
    max_gap : int             an occluded sample is filled when visible samples lie at most
                              this many frames before and after it (default ⌈s⌉; 0: never)

    Returns
    -------
    filtered : (F,M,3) float64   NaN where the support is too small (occluded samples inside
                                 a short gap are filled)

    Raises
    ------
    ValueError   wrong shape, negative or non-finite σ, degree outside 0 … 3
    """
    x = _as_markers(markers)
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"degree must be 0, 1, 2 or 3, got {degree}")
    if sigma_frames == AUTO:
        return filter_markers_auto(x, degree=degree)[0]
    if isinstance(sigma_frames, str) or not (np.isfinite(sigma_frames) and sigma_frames >= 0):
        raise ValueError(f"sigma_frames must be finite and >= 0 or {AUTO!r}, got {sigma_frames!r}")
    if sigma_frames == 0 or len(x) < 2:
        return x.copy()
    return _local_fit(x, float(sigma_frames), degree, min_support, max_gap)[0]


def _take_noise(x: np.ndarray) -> float:
    """:func:`temporal_noise` of a take (F ≥ 3), 0 where no marker is seen in three
    consecutive frames."""
    try:
        return temporal_noise(x)
    except ValueError:
        return 0.0


def filter_markers_auto(markers: np.ndarray, noise_mm: float | None = None,
                        bandwidths: tuple[float, ...] = AUTO_BANDWIDTHS, degree: int = DEGREE,
                        window_frames: float = RISK_WINDOW_FRAMES, truth: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`filter_markers` with the window chosen per marker and frame by Stein's unbiased
    risk estimate (SURE; Stein 1981), locally in time.

    For a linear smoother x̂ = S x of samples x = x* + ε, ε white with σ per coordinate,
    ``‖x − x̂‖² − Nσ² + 2σ² tr S`` is an unbiased estimate of the risk ``E‖x̂ − x*‖²``
    (Stein 1981, *Ann. Statist.* 9(6); for a linear smoother it is Mallows' C_p, Hastie,
    Tibshirani & Friedman, *Elements of Statistical Learning* §7.5); the local polynomial
    fit's trace terms are its hat values h(t) (:func:`_local_fit`). Per sample of marker m and window s the three coordinates give

        r_t(s) = ‖x_t − x̂_t(s)‖² + 6σ² h_t(s)     (the −3σ² the same for every s),

    s = 0 being the sample itself (r = 6σ²). The risk is summed over a Gaussian window of
    ``window_frames`` around each frame (visible samples only) and each (t, m) takes the s
    of least local risk: a marker at rest gets the widest window, an expression's fast onset
    a narrow one or none, and clean markers (σ → 0) keep their samples (every s > 0 has a
    residual, the sample itself none). σ defaults to :func:`temporal_noise` of the input.
    Where a window's fit is undefined (too little support) the sample stands for it; an
    occluded sample takes the fit of the window chosen for it, NaN where none fills it.

    Parameters
    ----------
    markers : (F,M,3) float   positions per frame, mm; NaN rows occluded (head-aligned:
                              :func:`filter_performance`)
    noise_mm : float          σ per coordinate, mm (default: estimated)
    bandwidths : floats       the candidate windows s, frames (0: no filtering)
    window_frames : float     σ of the Gaussian over which the risk is summed, frames
    truth : (F,M,3) float     the noise-free samples, for a bound in benchmarks: each window
                              is then chosen by its true squared error ‖x*_t − x̂_t(s)‖²,
                              summed over the same risk window, in place of SURE (an oracle
                              no rule choosing among these windows with this locality beats)

    Returns
    -------
    filtered : (F,M,3) float64
    chosen : (F,M) float64     the window s each sample took, frames
    """
    x = _as_markers(markers)
    if len(x) < 3:
        return x.copy(), np.zeros(x.shape[:2])
    if noise_mm is None:
        noise_mm = _take_noise(x)
    sigma = float(noise_mm)
    visible = np.isfinite(x).all(axis=2)
    window = _gaussian(window_frames)[None]
    out, chosen, least = x.copy(), np.zeros(x.shape[:2]), np.full(x.shape[:2], np.inf)
    for s in bandwidths:
        fit, hat = (x, np.ones(x.shape[:2])) if s == 0 else _local_fit(x, float(s), degree, None, None)
        undefined = visible & ~np.isfinite(hat)
        fit = np.where(undefined[..., None], x, fit)
        hat = np.where(undefined, 1.0, hat)
        r = np.where(visible, np.sum((x - fit) ** 2, axis=-1) + 6.0 * sigma ** 2 * hat
                     if truth is None else np.nan_to_num(np.sum((truth - fit) ** 2, axis=-1)), 0.0)
        risk = _moments(r, window)[0]
        better = risk < least               # strict: the first of equal risks wins
        out[better], chosen[better], least[better] = fit[better], s, risk[better]
    return out, chosen


@dataclass(frozen=True)
class MarkerModes:
    """The orthonormal modes of a marker-driven model's learned prior, in which ``"auto"``
    chooses its windows (the module docstring).

    Attributes
    ----------
    rest : (M,3) float64        the model's rest markers: the frame its prior is in, mm
    vectors : (3M,3M) float64   the prior covariance's eigenvectors, orthonormal columns by
                                decreasing eigenvalue (row-major (marker, xyz))
    weights : (M,) float64      the model's head-alignment weights (its stable markers), so
                                the frames are aligned as the prior's were
    """

    rest: np.ndarray
    vectors: np.ndarray
    weights: np.ndarray

    @classmethod
    def of(cls, rest: np.ndarray, prior: MarkerPrior | None, weights: np.ndarray,
           eigen: PriorEigen | None = None) -> "MarkerModes | None":
        """The modes of ``prior`` over displacements from ``rest`` (M,3), aligned with
        ``weights`` (M,); None without a prior. ``eigen``: the prior's decomposition where the
        caller already holds it (:class:`~service.geometry.marker_prior.PriorEigen`)."""
        if prior is None:
            return None
        eigen = PriorEigen.of(prior) if eigen is None else eigen
        return cls(np.asarray(rest, np.float64), np.ascontiguousarray(eigen.vectors[:, ::-1]),
                   np.asarray(weights, np.float64))


def filter_modes(u: np.ndarray, vectors: np.ndarray, noise_mm: float | None = None,
                 bandwidths: tuple[float, ...] = MODE_BANDWIDTHS, degree: int = DEGREE,
                 truth: np.ndarray | None = None) -> np.ndarray:
    """:func:`filter_markers_auto` of the coefficients ``c = Uᵀ u`` of each frame in an
    orthonormal basis U, then back: ``û = U ĉ``. The risk is summed over consecutive
    triples of columns as over a marker's three coordinates, so U's columns are best
    ordered by variance (:class:`MarkerModes`). With U = I it is
    :func:`filter_markers_auto` itself.

    Parameters
    ----------
    u : (F,M,3) float          head-aligned marker displacements (or positions), mm; NaN rows occluded
    vectors : (3M,3M) float    U, orthonormal columns
    noise_mm : float           σ per coordinate, mm (default: :func:`temporal_noise` of u)
    bandwidths, degree, truth  as :func:`filter_markers_auto` (``truth`` (F,M,3) as u)

    Returns
    -------
    (F,M,3) float64   the filtered frames; NaN for every frame with an occluded marker (a
                      coefficient needs every marker: such frames are gaps for the others)
    """
    u = _as_markers(u)
    F, M, _ = u.shape
    U = np.asarray(vectors, np.float64)
    if U.shape != (3 * M, 3 * M):
        raise ValueError(f"the basis must be ({3 * M},{3 * M}) for {M} markers, got {U.shape}")
    if noise_mm is None and len(u) >= 3:      # the coordinates' noise: the basis keeps it white
        noise_mm = _take_noise(u)
    full = np.isfinite(u).all(axis=(1, 2))
    coefficients = np.full((F, 3 * M), np.nan)
    coefficients[full] = u[full].reshape(-1, 3 * M) @ U
    if truth is not None:
        truth = (_as_markers(truth).reshape(F, 3 * M) @ U).reshape(F, M, 3)
    fitted, _ = filter_markers_auto(coefficients.reshape(F, M, 3), noise_mm, bandwidths, degree,
                                    truth=truth)
    out = np.full_like(u, np.nan)
    out[full] = (fitted[full].reshape(-1, 3 * M) @ U.T).reshape(-1, M, 3)
    return out


def filter_performance(markers: np.ndarray, sigma_frames: float | str = SIGMA_FRAMES, degree: int = DEGREE,
                       weights: np.ndarray | None = None, modes: MarkerModes | None = None,
                       mode_bandwidths: tuple[float, ...] = MODE_BANDWIDTHS,
                       truth: np.ndarray | None = None) -> np.ndarray:
    """:func:`filter_markers` in a head-aligned frame: rigid motion removed, filtered, restored.

    Each frame is rigidly aligned (Kabsch over its visible markers, :func:`rigid_align`)
    onto a reference, the mean of the performance's frames aligned to its most complete
    frame; the aligned trajectories are filtered and each frame's own transform is undone.
    So the expression is smoothed in time and the head pose stays as measured per frame.
    With ``modes`` and ``"auto"`` the frames are aligned with the modes' weights onto a
    reference aligned to their rest markers, and those with every marker are filtered in the
    modes (:func:`filter_modes`; the module docstring), the others per coordinate.

    Parameters
    ----------
    markers : (F,M,3) float    world marker positions, mm; NaN rows occluded
    sigma_frames, degree       as :func:`filter_markers`
    weights : (M,) float       per-marker weights of the rigid fits (default: the modes',
                               else 1)
    modes : MarkerModes        the model's prior modes (M markers), for ``"auto"``
    mode_bandwidths : floats   the windows ``"auto"`` chooses among in the modes, frames
    truth : (F,M,3) float      the noise-free world markers, for a bound in benchmarks: in
                               the modes, each window chosen by its true error
                               (:func:`filter_markers_auto`), aligned by the frames' own
                               transforms

    Returns
    -------
    filtered : (F,M,3) float64   world positions; NaN where :func:`filter_markers` leaves
                                 them; a frame with fewer than 3 visible markers is
                                 returned as given (and is a gap for its neighbours)
    """
    x = _as_markers(markers)
    if sigma_frames == 0 or len(x) < 2:
        return filter_markers(x, sigma_frames, degree)
    in_modes = modes is not None and sigma_frames == AUTO
    if in_modes and weights is None:
        weights = modes.weights
    visible = np.isfinite(x).all(axis=2)
    usable = visible.sum(axis=1) >= MIN_POINTS
    if not usable.any():
        return filter_markers(x, sigma_frames, degree)
    first = x[int(np.argmax(visible.sum(axis=1)))]
    ref_mask = np.isfinite(first).all(axis=1)
    aligned = np.full_like(x, np.nan)
    for f in np.flatnonzero(usable):              # 1st pass: onto the most complete frame
        if (visible[f] & ref_mask).sum() >= MIN_POINTS:
            aligned[f] = rigid_align(np.where(ref_mask[:, None], x[f], np.nan), first, weights).apply(x[f])
    ref = np.nanmean(aligned, axis=0) if np.isfinite(aligned).any() else first
    ref = np.where(np.isfinite(ref), ref, first)
    if in_modes:                                  # the reference in the prior's frame
        ref = rigid_align(ref, modes.rest, weights).apply(ref)
    transforms = {}
    aligned[:] = np.nan
    true = None if truth is None else np.full_like(x, np.nan)
    for f in np.flatnonzero(usable):
        ok = visible[f] & np.isfinite(ref).all(axis=1)
        if ok.sum() >= MIN_POINTS:
            T = rigid_align(np.where(ok[:, None], x[f], np.nan), ref, weights)
            transforms[f] = T
            aligned[f] = T.apply(x[f])
            if true is not None:
                true[f] = T.apply(np.asarray(truth[f], np.float64))
    if in_modes:
        smooth = filter_modes(aligned - modes.rest, modes.vectors, None, mode_bandwidths, degree,
                              None if true is None else true - modes.rest) + modes.rest
        full = np.isfinite(smooth).all(axis=(1, 2))
        if not full.all():                        # the others per coordinate
            smooth = np.where(full[:, None, None], smooth, filter_markers(aligned, sigma_frames, degree))
    else:
        smooth = filter_markers(aligned, sigma_frames, degree)
    out = x.copy()
    for f, T in transforms.items():
        out[f] = T.inverse().apply(smooth[f])
    return out

