"""A learned Gaussian prior over marker displacements, and the per-frame MAP denoiser it gives.

Issue 17, failure mode 4: optical-mocap noise (σ ≈ 0.3 mm per coordinate) on the markers
that drive ma2008's large-scale step (the linear thin shell of bickel2008 §4, which
interpolates the markers exactly) goes straight into the surface. The shell prior alone
(:func:`~service.geometry.thin_shell.soft_handles`) cannot tell noise from deformation: a
smooth shell prior gives every marker configuration of the same bending energy the same
probability. The training frames can: a face's marker displacements lie close to a
low-dimensional span.

Two estimators of that prior's covariance C over the flattened, head-aligned training
displacements ``x ∈ R^{3M}`` (M markers, row-major (marker, xyz)), mean μ the sample mean:

* :meth:`MarkerPrior.fit_ppca`, **probabilistic PCA** (Tipping & Bishop 1999,
  "Probabilistic principal component analysis", J. R. Statist. Soc. B 61(3), eq. 7-8):
  ``C = U_k diag(l) U_kᵀ + δ (I − U_k U_kᵀ)``, the isotropic variance floored at a fraction
  of the mean per-coordinate variance (T&B's ML value, the mean discarded eigenvalue, is
  tiny on a few training clips and crushes everything outside their span). Measured, it
  fails on the sample actors: family a's 8 symmetric training clips span 8 dimensions and
  the held-out in-range and combination performances (one-sided smiles and brows, new
  combinations) have 0.52 mm RMS of marker displacement outside even a 32-dimensional
  training span, more than the noise (0.30 mm); so the prior's best setting (floor 3 %)
  costs clean markers +0.10 mm of face mean error (0.388 → 0.485 mm at σ = 0.3) and takes
  only 0.637 → 0.564 mm off the noisy ones. Kept for the benchmark's rows.
* :meth:`MarkerPrior.fit_tapered`, the **default**: the sample covariance tapered by a
  compactly supported correlation of the rest markers' distance (covariance tapering /
  localization: Furrer & Bengtsson 2007, "Estimation of high-dimensional prior and
  posterior covariance matrices in Kalman filter variants", J. Multivariate Anal. 98, §3,
  with the Gaspari & Cohn 1999 function, Q. J. R. Meteorol. Soc. 125, eq. 4.10), plus a
  diagonal floor. A face's expressions are local: tapering keeps what the training shows
  within a region and drops the long-range couplings (left brow with right brow), so the
  one-sided and combined deformations stay plausible. Family a, σ = 0.3 mm, face mean vs
  truth (clean / noisy markers): exact interpolation 0.388 / 0.637, shell prior 0.454 /
  0.620, PPCA 0.485 / 0.564, tapered (defaults) 0.430 / 0.501 (``benchmarks/marker_denoise.py``).
  Rule chosen on family a (grid ℓ ∈ {0.75, 1, 1.5, 2}, f ∈ {0.003, 0.01, 0.03}: the lowest
  mean of clean and noisy error) and confirmed on family b (README, "Noisy markers").
  The grid extended beyond its edge ℓ = 2 (ℓ ∈ {2, 4, 6, 8, 12, ∞}, f ∈ {0.001, 0.003,
  0.01}, σ = 0.3, same rule): on the PDM's prior (the ``train_*`` clips) ℓ = 2, f = 0.01
  stays the optimum (clean / noisy 0.430 / 0.501 mm; ℓ = 4: 0.441 / 0.496, ℓ = 8: 0.454 /
  0.500, ∞: 0.538 / 0.574); on shape space's prior (the ``database`` performance) family a
  prefers ever longer tapers (ℓ = 2: 0.408 / 0.478, ℓ = 12: 0.406 / 0.441, ∞ f = 0.003:
  0.407 / 0.439), but family b refutes it: its combinations go 0.515 → 0.625 (ℓ = 12) and
  0.756 (∞) mm on clean markers (mean over the three performances 0.451 / 0.513 at ℓ = 2
  against 0.486 / 0.529 and 0.530 / 0.567), because b's database never shows its
  combinations and the long-range couplings it learns are wrong for them. So ℓ = 2 stays
  for both (``benchmarks/marker_denoise.py --prior-source train|database``).

Measured and not kept: a target diagonal in the shell energy's eigenbasis (the training
energy per shell mode, correlations between modes dropped): noisy 0.555 mm at best on
family a, because facial motion is not sparse in those modes; adding the shell prior
(β = 1) to either learned prior made both clean and noisy results worse on family a
(e.g. PPCA 3 %: noisy 0.564 → 0.583 mm), so :data:`SHELL_WEIGHT` is 0.

Every marker-driven method takes its denoiser from one constructor,
:func:`marker_denoiser` (σ = 0: exact interpolation; σ > 0: the learned prior's
:class:`MarkerDenoiser`, or the shell prior's :class:`ShellDenoiser` for a model saved
before the learned prior; ``"auto"``: :class:`AdaptiveDenoiser`, σ estimated per request by
:func:`frame_noise`). For a performance of consecutive frames :func:`temporal_noise` is the
sharper estimate; :func:`noise_confidence` turns an estimate into a confidence factor.

The denoiser (:class:`MarkerDenoiser`) is the MAP estimate of the true displacements x
from the visible noisy ones m (Gaussian noise σ per coordinate) under the product of this
prior and the shell prior ``exp(−xᵀ(G⊗I₃)x / 2τ²)``
(:func:`~service.geometry.thin_shell.shell_prior_scale`), weighted by ``shell_weight`` β:

    (D_V + σ² Q + β σ²/τ² G⊗I₃) x = D_V m + σ² Q μ,     Q = C⁻¹,

a (3M)×(3M) symmetric positive definite system, inverted once for frames with every
marker; a frame with occluded markers needs only a (3|U|)×(3|U|) solve for its |U|
occluded ones (Woodbury, :meth:`MarkerDenoiser.__call__`). Occluded markers (NaN) drop
out of D_V and are completed by the prior's conditional mean given the visible ones, or,
where the visible ones leave a marker uncertain under the prior, by the shell's minimum
energy (:func:`shell_completion`). σ → 0 gives back the visible markers exactly; σ = 0
itself is the papers' exact interpolation of the visible markers, bit for bit, with the
occluded ones completed by that limit (:class:`PriorCompletion`; without a learned prior by
minimum energy, :func:`~service.geometry.thin_shell.soft_handles` at λ = 0).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from service.geometry.thin_shell import as_frames, marker_noise_ratio, soft_handle_operator, soft_handles

#: default floor δ of :meth:`MarkerPrior.fit_ppca`, a fraction of the mean per-coordinate
#: training variance tr S / 3M (its best on family a, benchmarks/marker_denoise.py)
FLOOR_FRACTION = 0.03
#: default taper length L of :meth:`MarkerPrior.fit_tapered`, a fraction of the rest
#: markers' RMS radius
LENGTH_FRACTION = 2.0
#: default floor δ of :meth:`MarkerPrior.fit_tapered`, a fraction of tr S / 3M
TAPER_FLOOR_FRACTION = 0.01
#: default weight β of the shell prior beside the learned one (0: measured worse on family a)
SHELL_WEIGHT = 0.0
#: an occluded marker whose conditional variance under the prior, given the frame's visible
#: markers, is above this fraction of its prior variance is completed by the shell's minimum
#: energy instead of the prior's conditional mean (:func:`shell_completion`)
SHELL_COMPLETION_RATIO = 0.2


@dataclass(frozen=True)
class MarkerPrior:
    """Gaussian prior over marker displacements (M markers): ``x ~ N(mean, covariance)``.

    Attributes
    ----------
    mean : (M,3) float64              μ, the mean training displacement, mm
    covariance : (3M,3M) float64      C, symmetric positive definite, mm² (row-major (marker, xyz))
    """

    mean: np.ndarray
    covariance: np.ndarray

    @staticmethod
    def _samples(samples: np.ndarray) -> np.ndarray:
        x = np.asarray(samples, dtype=np.float64)
        if x.ndim != 3 or x.shape[2] != 3:
            raise ValueError(f"samples must be (F,M,3), got {x.shape}")
        x = x[np.isfinite(x).all(axis=(1, 2))]
        if len(x) < 2:
            raise ValueError("the marker prior needs at least 2 frames with every marker")
        return x

    @classmethod
    def fit_ppca(cls, samples: np.ndarray, floor_fraction: float = FLOOR_FRACTION) -> "MarkerPrior":
        """PPCA (Tipping & Bishop 1999, eq. 7-8) of sample displacements (F,M,3), mm, with
        the isotropic variance floored at δ = ``floor_fraction`` · tr S / 3M and every
        eigenvalue above δ kept (frames with a NaN are skipped)."""
        if not 0 < floor_fraction <= 1:
            raise ValueError(f"the floor fraction must be in (0, 1], got {floor_fraction}")
        x = cls._samples(samples)
        F, M, _ = x.shape
        mu = x.mean(axis=0)
        X = (x - mu).reshape(F, 3 * M)
        _, s, Vt = np.linalg.svd(X, full_matrices=False)
        ev = s ** 2 / F
        delta = max(float(floor_fraction) * float(ev.sum()) / (3 * M), 1e-12)
        U, l = Vt[ev > delta].T, ev[ev > delta]
        C = (U * (l - delta)) @ U.T
        C[np.diag_indices_from(C)] += delta
        return cls(mu, 0.5 * (C + C.T))

    @classmethod
    def fit_tapered(cls, samples: np.ndarray, rest: np.ndarray, length_fraction: float = LENGTH_FRACTION,
                    floor_fraction: float = TAPER_FLOOR_FRACTION) -> "MarkerPrior":
        """Tapered sample covariance of displacements (F,M,3), mm, of markers at ``rest`` (M,3).

        ``C = S ∘ (ρ(D / L) ⊗ 1₃ₓ₃) + δ I`` (Furrer & Bengtsson 2007, §3; frames with a NaN
        skipped): S the sample covariance, D the rest markers' distances, ρ the compactly
        supported Gaspari & Cohn (1999, eq. 4.10) correlation (ρ(0) = 1, 0 beyond 2L), L =
        ``length_fraction`` × the rest markers' RMS radius about their centroid (so the rule
        does not depend on the actor's unit or size), δ = ``floor_fraction`` · tr S / 3M.
        The Schur product with a positive definite taper stays positive semidefinite; it
        keeps the training's local correlations (a brow's markers move together) and drops
        the long-range ones (the left brow with the right), so a deformation the clips only
        showed symmetrically is plausible on one side alone.
        """
        if not length_fraction > 0:
            raise ValueError(f"the taper length must be > 0, got {length_fraction}")
        if not 0 < floor_fraction <= 1:
            raise ValueError(f"the floor fraction must be in (0, 1], got {floor_fraction}")
        x = cls._samples(samples)
        F, M, _ = x.shape
        rest = np.asarray(rest, np.float64)
        if rest.shape != (M, 3):
            raise ValueError(f"rest markers must be ({M},3), got {rest.shape}")
        mu = x.mean(axis=0)
        X = (x - mu).reshape(F, 3 * M)
        S = X.T @ X / F
        L = float(length_fraction) * float(np.sqrt(((rest - rest.mean(axis=0)) ** 2).sum(axis=1).mean()))
        D = np.linalg.norm(rest[:, None] - rest[None], axis=-1)
        C = S * np.kron(gaspari_cohn(D / max(L, 1e-12)), np.ones((3, 3)))
        C[np.diag_indices_from(C)] += max(float(floor_fraction) * float(np.trace(S)) / (3 * M), 1e-12)
        return cls(mu, 0.5 * (C + C.T))

    @property
    def n_markers(self) -> int:
        return len(self.mean)

    def precision(self) -> np.ndarray:
        """Q = C⁻¹ (3M,3M), mm⁻²."""
        Q = np.linalg.inv(self.covariance)
        return 0.5 * (Q + Q.T)

    def arrays(self, prefix: str = "marker_prior_") -> dict[str, np.ndarray]:
        """The prior as named arrays (for a model's npz); :meth:`from_arrays` reads them."""
        return {f"{prefix}mean": self.mean, f"{prefix}covariance": self.covariance}

    @classmethod
    def from_arrays(cls, a, prefix: str = "marker_prior_") -> "MarkerPrior | None":
        """The prior stored by :meth:`arrays` in the mapping ``a``; None when ``a`` has none
        (a model saved before the prior existed)."""
        if f"{prefix}mean" not in a:
            return None
        return cls(np.asarray(a[f"{prefix}mean"], np.float64), np.asarray(a[f"{prefix}covariance"], np.float64))


def gaspari_cohn(r: np.ndarray) -> np.ndarray:
    """Gaspari & Cohn (1999, eq. 4.10) compactly supported correlation of r = distance / L
    (any shape): a fifth-order piecewise rational, 1 at 0, 0 for r ≥ 2, positive definite in
    three dimensions."""
    r = np.abs(np.asarray(r, dtype=np.float64))
    out = np.zeros_like(r)
    a, b = r <= 1, (r > 1) & (r < 2)
    x = r[a]
    out[a] = -0.25 * x ** 5 + 0.5 * x ** 4 + 0.625 * x ** 3 - 5.0 / 3.0 * x ** 2 + 1.0
    x = r[b]
    out[b] = x ** 5 / 12.0 - 0.5 * x ** 4 + 0.625 * x ** 3 + 5.0 / 3.0 * x ** 2 - 5.0 * x + 4.0 - 2.0 / (3.0 * x)
    return out


def _system(prior: MarkerPrior, G: np.ndarray, noise_mm: float, shell_ratio: float):
    """``A = σ² Q + λ G⊗I₃`` (3M,3M) and ``b = σ² Q μ`` (3M,) of the MAP normal equations."""
    s2 = float(noise_mm) ** 2
    Q = prior.precision()
    A = s2 * Q + shell_ratio * np.kron(np.asarray(G, np.float64), np.eye(3))
    return A, s2 * (Q @ prior.mean.ravel())


@dataclass(frozen=True)
class MarkerDenoiser:
    """Per-frame MAP marker displacements under the learned prior and the shell prior.

    Attributes
    ----------
    prior : MarkerPrior
    energy : (M,M) float64     handle energy G of the thin shell (:func:`handle_energy_matrix`)
    noise_mm : float           σ ≥ 0 per coordinate, mm (0: exact interpolation)
    shell_ratio : float        β σ²/τ² (τ the shell prior's scale; 0 without the shell prior)
    full : (3M,3M) or None     ``(I + A)⁻¹`` for frames with every marker (None when σ = 0)
    offset : (3M,) or None     ``(I + A)⁻¹ b``
    eigen : PriorEigen or None  the prior's eigendecomposition (:func:`shell_completion`;
                               None when σ = 0)
    """

    prior: MarkerPrior
    energy: np.ndarray
    noise_mm: float
    shell_ratio: float
    full: np.ndarray | None = None
    offset: np.ndarray | None = None
    eigen: "PriorEigen | None" = None

    @classmethod
    def build(cls, prior: MarkerPrior, G: np.ndarray, noise_mm: float, prior_scale_mm: float,
              shell_weight: float = SHELL_WEIGHT) -> "MarkerDenoiser":
        """The denoiser for noise σ = ``noise_mm`` with the shell prior of scale τ =
        ``prior_scale_mm`` (mm) weighted by β = ``shell_weight`` (0: learned prior only)."""
        G = np.asarray(G, np.float64)
        if G.shape != (prior.n_markers,) * 2:
            raise ValueError(f"energy {G.shape} does not match a prior of {prior.n_markers} markers")
        if not (noise_mm >= 0 and np.isfinite(noise_mm)):
            raise ValueError(f"marker noise must be finite and >= 0 mm, got {noise_mm}")
        ratio = 0.0
        if shell_weight and noise_mm:
            if not (prior_scale_mm > 0 and np.isfinite(prior_scale_mm)):
                raise ValueError(f"the shell prior's scale must be finite and > 0 mm, got {prior_scale_mm}")
            ratio = float(shell_weight) * float(noise_mm) ** 2 / float(prior_scale_mm) ** 2
        if noise_mm == 0:
            return cls(prior, G, 0.0, 0.0)
        A, b = _system(prior, G, noise_mm, ratio)
        Ainv = np.linalg.inv(A + np.eye(len(A)))
        Ainv = 0.5 * (Ainv + Ainv.T)
        return cls(prior, G, float(noise_mm), ratio, Ainv, Ainv @ b, PriorEigen.of(prior))

    @property
    def interpolates(self) -> bool:
        """True when visible markers pass unchanged (σ = 0)."""
        return self.noise_mm == 0

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Denoised complete displacements (F,M,3) (or (M,3)) of marker displacements u,
        mm, NaN rows for occluded markers.

        Raises
        ------
        ValueError   a frame with no visible marker
        """
        M = self.prior.n_markers
        u, batched = as_frames(u, M)
        if self.noise_mm == 0:
            out = soft_handles(self.energy, u, 0.0)
            return out if batched else out[0]
        F = len(u)
        full, groups = occlusion_groups(u)
        out = np.empty((F, 3 * M))
        if full.any():
            out[full] = u[full].reshape(-1, 3 * M) @ self.full + self.offset   # full is symmetric
        # occluded frames: (I + A − E Eᵀ)⁻¹ by Woodbury from the precomputed (I + A)⁻¹ = P, E
        # selecting the occluded coordinates: x = y + P E (I − Eᵀ P E)⁻¹ Eᵀ y, y = P (D_V m + b)
        P = self.full
        for sel, idx in groups:
            y = np.nan_to_num(u[sel].reshape(len(sel), 3 * M)) @ P + self.offset
            S = np.eye(len(idx)) - P[np.ix_(idx, idx)]
            out[sel] = y + np.linalg.solve(S, y[:, idx].T).T @ P[idx]
        out = shell_completion(self.energy, self.eigen, u, out.reshape(F, M, 3))
        return out if batched else out[0]


@dataclass(frozen=True)
class ShellDenoiser:
    """Per-frame MAP marker displacements under the thin shell's energy alone (a model saved
    before the learned prior existed, or σ = 0): :func:`~service.geometry.thin_shell.soft_handles`.

    Attributes
    ----------
    energy : (M,M) float64          handle energy G of the thin shell
    ratio : float                   λ = σ²/τ² ≥ 0 (0: exact interpolation, minimum-energy completion)
    operator : (M,M) or None        ``(I + λG)⁻¹`` for frames with every marker (None when λ = 0)
    """

    energy: np.ndarray
    ratio: float
    operator: np.ndarray | None = None

    @property
    def interpolates(self) -> bool:
        """True when visible markers pass unchanged (λ = 0, the papers' exact interpolation)."""
        return self.ratio == 0

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Denoised complete displacements, same shape as u (F,M,3) or (M,3), mm (NaN rows:
        occluded markers)."""
        return soft_handles(self.energy, u, self.ratio, self.operator)


@dataclass(frozen=True)
class PriorCompletion:
    """σ = 0 with a learned prior: the papers' exact interpolation of the visible markers,
    the occluded ones completed by the prior's conditional mean given them
    (:meth:`PriorEigen.conditional_mean`, the σ → 0 limit of :class:`MarkerDenoiser`'s MAP
    estimate), or by the shell's minimum energy where the visible ones leave a marker
    uncertain under the prior (:func:`shell_completion`, the same rule as at σ > 0). Frames
    with every marker pass unchanged (bit for bit :class:`ShellDenoiser` at λ = 0).

    Why (issue 17): a burst of occluded markers left the thin shell's minimum-energy fill
    flat under them (a cheek or a mouth corner that stays at rest while the face moves),
    and every marker-driven method built on it inherited the error. Measured with
    ``generalization_report.py`` (level 0, 8 frames per performance, the cached σ = 0
    models; PDM biquadratic, face mean / max mm on the occluded performances, before →
    after): family b in range 0.221 / 6.87 → 0.024 / 0.45, combinations 0.242 / 3.91 →
    0.182 / 2.99, out of range 0.298 / 10.98 → 0.091 / 3.62; family a in range 0.131 /
    2.60 → 0.112 / 1.34, combinations 0.134 / 2.61 → 0.119 / 2.57, out of range 0.154 /
    6.45 → 0.039 / 0.59 (chosen from b's failure, confirmed on a). Clean and noisy
    performances (no occlusion) are bit for bit unchanged, every method.

    Attributes
    ----------
    energy : (M,M) float64     handle energy G of the thin shell
    prior : MarkerPrior
    """

    energy: np.ndarray
    prior: MarkerPrior

    @property
    def interpolates(self) -> bool:
        """True: visible markers pass unchanged."""
        return True

    @functools.cached_property
    def eigen(self) -> "PriorEigen":
        """The prior's eigendecomposition, made on the first occluded frame (a level-1
        model's load does not pay for it)."""
        return PriorEigen.of(self.prior)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Complete displacements, same shape as u (F,M,3) or (M,3), mm (NaN rows: occluded
        markers).

        Raises
        ------
        ValueError   a frame with no visible marker
        """
        u, batched = as_frames(u, self.prior.n_markers)
        if np.isfinite(u).all():
            out = soft_handles(self.energy, u, 0.0)
        else:
            out = shell_completion(self.energy, self.eigen, u, self.eigen.conditional_mean(u))
        return out if batched else out[0]


#: ``marker_noise_mm`` value asking for σ estimated per request (:class:`AdaptiveDenoiser`)
AUTO = "auto"
#: prior directions whose variance is at most this multiple of the median eigenvalue of C
#: count as the prior's floor, where a frame's residual is noise (:func:`frame_noise`)
FLOOR_DIRECTIONS = 1.5
#: median of the χ²₁ distribution (scipy.stats.chi2.ppf(0.5, 1)): median(z²) = 0.4549 σ²
#: for z ~ N(0, σ²)
CHI2_1_MEDIAN = 0.45493642311957283
#: σ (mm) of the near-exact fill of occluded markers before :func:`frame_noise` projects a
#: frame (the prior's conditional mean of the occluded given the visible ones)
FILL_NOISE_MM = 1e-3


@dataclass(frozen=True)
class PriorEigen:
    """The eigendecomposition ``C = U diag(c) Uᵀ`` of a prior's covariance, so the MAP
    estimate of :class:`MarkerDenoiser` is had for any σ without a (3M)×(3M) inverse:
    ``P = (I + σ²Q)⁻¹ = U diag(w) Uᵀ`` with the Wiener gains ``w = c / (c + σ²)``, and for a
    frame with every marker ``x = μ + U (w ∘ Uᵀ(m − μ))`` (two (3M)×(3M) products); occluded
    coordinates by the same Woodbury update as :meth:`MarkerDenoiser.__call__`, on the rows
    of P it needs, with ``I − P_UU = U_U diag(1 − w) U_Uᵀ`` computed without cancellation.
    Equal to :class:`MarkerDenoiser`'s solve within rounding (tests: 1e-9 mm).

    Attributes
    ----------
    mean : (3M,) float64        μ, mm
    values : (3M,) float64      c, the eigenvalues of C (ascending, clipped at 0), mm²
    vectors : (3M,3M) float64   U, orthonormal columns
    """

    mean: np.ndarray
    values: np.ndarray
    vectors: np.ndarray

    @classmethod
    def of(cls, prior: MarkerPrior) -> "PriorEigen":
        c, U = np.linalg.eigh(prior.covariance)
        return cls(prior.mean.ravel().copy(), np.clip(c, 0.0, None), np.ascontiguousarray(U))

    def floor_directions(self) -> np.ndarray:
        """(3M,k) the eigenvectors with eigenvalues ≤ :data:`FLOOR_DIRECTIONS` × their median."""
        return np.ascontiguousarray(self.vectors[:, self.values <= FLOOR_DIRECTIONS * np.median(self.values)])

    def conditional_variance_ratio(self, idx: np.ndarray) -> np.ndarray:
        """Per occluded marker (k,) of the occluded coordinates ``idx`` (3k,) (whole markers, in
        order): its variance under the prior given every other coordinate,
        ``tr((Q_UU)⁻¹)_m`` (Q = C⁻¹; the noise-free conditional, Rasmussen & Williams 2006,
        eq. A.6, in its precision form), over its prior variance ``tr(C_mm)``; in [0, 1], 0
        when the visible markers determine it, 1 when they say nothing about it."""
        Ui = self.vectors[idx]
        Q_UU = (Ui / np.maximum(self.values, 1e-300)) @ Ui.T
        conditional = np.diag(np.linalg.inv(Q_UU)).reshape(-1, 3).sum(axis=1)
        prior = ((Ui ** 2) @ self.values).reshape(-1, 3).sum(axis=1)
        return conditional / np.maximum(prior, 1e-300)

    def conditional_mean(self, u: np.ndarray) -> np.ndarray:
        """Complete displacements (F,M,3) of head-aligned displacements u (F,M,3), mm, NaN rows
        occluded: the visible markers as they are and the occluded ones the prior's mean given
        them, ``x_U = μ_U − (Q_UU)⁻¹ Q_UV (m_V − μ_V)`` (Q = C⁻¹; the noise-free conditional,
        Rasmussen & Williams 2006, eq. A.6, in its precision form) — the σ → 0 limit of the MAP
        estimate :meth:`map`. One (3k)×(3k) solve per occlusion pattern of k hidden markers.

        Raises
        ------
        ValueError   a frame with no visible marker
        """
        u = np.asarray(u, np.float64)
        n = len(self.mean)
        F = len(u)
        _, groups = occlusion_groups(u)
        out = u.reshape(F, n).copy()
        inverse = 1.0 / np.maximum(self.values, 1e-300)
        for sel, idx in groups:
            Qi = (self.vectors[idx] * inverse) @ self.vectors.T                    # Q[idx] (3k,3M)
            d = np.nan_to_num(out[sel] - self.mean)                                # occluded rows 0
            d[:, idx] = 0.0
            out[np.ix_(sel, idx)] = self.mean[idx] - np.linalg.solve(Qi[:, idx], (d @ Qi.T).T).T
        return out.reshape(u.shape)

    def map(self, u: np.ndarray, noise_mm: float) -> np.ndarray:
        """MAP displacements (F,M,3) (or (M,3)) of head-aligned displacements u, mm, NaN rows
        occluded, under noise σ = ``noise_mm`` > 0 (no shell term).

        Raises
        ------
        ValueError   a frame with no visible marker; σ not > 0
        """
        if not (noise_mm > 0 and np.isfinite(noise_mm)):
            raise ValueError(f"the MAP solve needs a finite σ > 0, got {noise_mm}")
        n = len(self.mean)
        u, batched = as_frames(u, n // 3)
        s2 = float(noise_mm) ** 2
        w = self.values / (self.values + s2)
        U, mu = self.vectors, self.mean
        F = len(u)
        x = u.reshape(F, n)
        full, groups = occlusion_groups(u)
        out = np.empty((F, n))
        if full.any():
            out[full] = mu + ((x[full] - mu) @ U * w) @ U.T
        for sel, idx in groups:
            y = mu + ((np.nan_to_num(x[sel]) - mu) @ U * w) @ U.T            # P (D_V m + b)
            P_rows = (U[idx] * w) @ U.T                                       # P[idx]
            S = (U[idx] * (s2 / (self.values + s2))) @ U[idx].T              # I − P[idx, idx]
            out[sel] = y + np.linalg.solve(S, y[:, idx].T).T @ P_rows
        out = out.reshape(F, n // 3, 3)
        return out if batched else out[0]


def occlusion_groups(u: np.ndarray) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """Frames of marker displacements u (F,M,3), NaN where occluded, grouped for the MAP
    solves: ``full`` (F,) bool (every marker seen) and, per occlusion pattern of the others,
    (its frames (k,), its occluded coordinates (3·missing,) of the flattened (3M,) frame).

    Raises ValueError for a frame with no visible marker."""
    missing = ~np.isfinite(u).all(axis=2)                                      # (F,M)
    full = ~missing.any(axis=1)
    if full.all():
        return full, []
    patterns, which = np.unique(missing[~full], axis=0, return_inverse=True)
    frames = np.flatnonzero(~full)
    if patterns.all(axis=1).any():
        raise ValueError("all markers are unknown; at least one is needed")
    return full, [(frames[which.ravel() == p], np.flatnonzero(np.repeat(miss, 3)))
                  for p, miss in enumerate(patterns)]


def shell_completion(energy: np.ndarray, eigen: "PriorEigen", u: np.ndarray, x: np.ndarray,
                     ratio: float = SHELL_COMPLETION_RATIO) -> np.ndarray:
    """The MAP displacements x (F,M,3) of marker displacements u (F,M,3) (NaN rows occluded),
    with every occluded marker whose :meth:`PriorEigen.conditional_variance_ratio` (given
    that frame's visible markers) is above ``ratio`` completed again by the shell's minimum
    energy given all the others (:func:`~service.geometry.thin_shell.soft_handles`, λ = 0, the
    papers' completion), instead of the prior's conditional mean; x itself when none is.

    Why (issue 17): the prior completes a hidden marker with what the training clips showed
    near it; where the visible markers leave it uncertain and the pose is a combination the
    clips never showed (family b's clips never combine), that guess is worse than the smooth
    shell's. Chosen on family b (``marker_noise_mm = "auto"``, the thin shell's face mean
    vertex error on every occluded frame of the held-out performances, ratio ∈ {∞, 0.8,
    0.6, 0.4, 0.2, 0.1, 0}: in range / combinations / out of range 0.290 / 0.511 / 0.541
    mm at ∞ (the prior for every marker), 0.290 / 0.483 / 0.549 at 0.2 (the lowest mean;
    max on combinations 7.21 → 6.93 mm), 0.380 / 0.504 / 0.663 at 0 (the shell for every
    marker)); confirmed harmless on family a (0.2768 / 0.4227 / 0.5039 → 0.2767 / 0.4227 /
    0.5039), where the prior completes well. At a fixed σ = 0.3 mm the same: b 0.298 /
    0.566 / 0.561 → 0.298 / 0.538 / 0.569, a 0.3444 / 0.4685 / 0.5187 → 0.3441 / 0.4685 /
    0.5187. The conditional variance is the prior's alone (noise-free), so the rule is the
    same for every σ and both MAP solves (:class:`MarkerDenoiser`, :class:`FixedNoise`).
    """
    full, groups = occlusion_groups(u)
    y = None
    for sel, idx in groups:
        uncertain = idx[::3][eigen.conditional_variance_ratio(idx) > ratio] // 3
        if uncertain.size:
            y = np.array(x, np.float64) if y is None else y
            y[np.ix_(sel, uncertain)] = np.nan
    return x if y is None else soft_handles(energy, y, 0.0)


def frame_noise(prior: MarkerPrior, u: np.ndarray, basis: np.ndarray | None = None,
                eigen: "PriorEigen | None" = None) -> np.ndarray:
    """Per-frame marker noise σ̂ (F,), mm per coordinate, from each frame's residual against
    the learned prior.

    Estimator: project ``u − μ`` on the prior's *floor directions* (eigenvectors of C whose
    eigenvalue is at most :data:`FLOOR_DIRECTIONS` × the median eigenvalue: the diagonal
    floor δ, the directions the training never moved in; 345 of 450 on family a) and take
    ``σ̂² = median_i z_i² / 0.4549`` (the median of χ²₁), i.e. the median absolute
    deviation about zero of the coordinates there, ``σ̂ = 1.4826 · median_i |z_i|`` (Hampel
    1974, the normal consistency factor 1/Φ⁻¹(3/4)). Assumptions: the noise is white, Gaussian, the same σ on every coordinate
    and independent of the deformation, so it spreads evenly over all 3M directions, while
    a face's deformation (smooth, low-dimensional) lies mostly in the prior's few leading
    directions; what a held-out frame does outside the training span is concentrated in a
    few smooth directions, which the median ignores (the mean would not: the Gaussian
    marginal likelihood of σ, N(μ, C + σ²I), reads those as noise and gives family a's
    clean in-range frames σ̂ up to 0.28 mm). Measured on family a's held-out frames
    (prior of the training clips): σ = 0.3 mm noisy markers give per-frame medians 0.299 –
    0.313 mm (p10–p90 0.28–0.41); clean markers 0.006 – 0.059 mm (p90 up to 0.26 mm on
    in-range frames far from the training span). The estimate is per frame, in any frame
    order, so it serves a single-frame request or a stream.

    Occluded markers (NaN) are first filled by the prior's conditional mean given the
    visible ones (a MAP solve at σ = :data:`FILL_NOISE_MM`), which carries no noise, so
    σ̂² is divided by the visible fraction of the coordinates.

    Parameters
    ----------
    prior : MarkerPrior
    u : (F,M,3) or (M,3) float     head-aligned marker displacements, mm, NaN rows occluded
    basis : (3M,k) float, optional  the floor directions (:func:`floor_directions`), precomputed
    eigen : PriorEigen, optional    the prior's eigendecomposition (the fill), precomputed

    Returns
    -------
    sigma : (F,) float64 (a float for one frame), mm
    """
    M = prior.n_markers
    u, batched = as_frames(u, M)
    if basis is None or (eigen is None and not np.isfinite(u).all()):
        eigen = PriorEigen.of(prior) if eigen is None else eigen
        basis = eigen.floor_directions() if basis is None else basis
    W = basis
    visible = np.isfinite(u).all(axis=2)                                          # (F,M)
    if not visible.all():
        u = eigen.map(u, FILL_NOISE_MM)
    z2 = ((u.reshape(len(u), 3 * M) - prior.mean.ravel()) @ W) ** 2              # (F,k)
    s2 = np.median(z2, axis=1) / CHI2_1_MEDIAN / np.maximum(visible.mean(axis=1), 1.0 / M)
    sigma = np.sqrt(s2)
    return sigma if batched else float(sigma[0])


def floor_directions(prior: MarkerPrior) -> np.ndarray:
    """The prior's floor directions (3M,k): orthonormal eigenvectors of C with eigenvalues at
    most :data:`FLOOR_DIRECTIONS` × their median (see :func:`frame_noise`)."""
    return PriorEigen.of(prior).floor_directions()


def temporal_noise(u: np.ndarray) -> float:
    """Marker noise σ̂ (mm per coordinate) of a performance of consecutive frames (F,M,3),
    F ≥ 3, head-aligned, NaN rows occluded: the robust MAD of its temporal second
    differences, ``σ̂ = 1.4826 · median |u_{t+1} − 2u_t + u_{t−1}| / √6``.

    Assumptions: noise white in time and space, Gaussian, σ the same everywhere (then a
    second difference carries variance (1 + 4 + 1) σ² = 6σ²; 1.4826 is the normal
    consistency factor of the MAD, Hampel 1974), and motion smooth at the capture rate (a
    second difference of the deformation itself small against √6 σ for most markers, which
    the median then ignores). Measured on family a's held-out performances at 30 frames/s:
    0.296 – 0.300 mm for σ = 0.3, 0.004 – 0.007 mm for clean markers. It needs consecutive
    frames: on frames far apart it measures the motion (a benchmark's subsampled frames,
    a stream's single frames), where :func:`frame_noise` serves.
    """
    u = np.asarray(u, np.float64)
    if u.ndim != 3 or len(u) < 3:
        raise ValueError(f"need (F,M,3) with F >= 3 consecutive frames, got {u.shape}")
    d2 = np.abs(u[2:] - 2.0 * u[1:-1] + u[:-2])
    d2 = d2[np.isfinite(d2)]
    if not d2.size:
        raise ValueError("no marker is visible in three consecutive frames")
    return float(1.4826 * np.median(d2) / np.sqrt(6.0))


def noise_confidence(prior: MarkerPrior, sigma: np.ndarray) -> np.ndarray:
    """The fraction of the marker space the markers still determine over noise σ (…), mm:
    ``tr(C (C + σ² I)⁻¹) / 3M`` in [0, 1], the effective degrees of freedom of the MAP
    (Wiener) filter over its dimension (the ridge hat-matrix trace, Hastie, Tibshirani &
    Friedman, *Elements of Statistical Learning*, eq. 3.50). 1 at σ = 0; on family a's
    prior 0.25 at σ = 0.3 mm (the floor directions, variance δ ≈ (0.16 mm)², are then
    mostly noise)."""
    return dof_fraction(np.clip(np.linalg.eigvalsh(prior.covariance), 0.0, None), sigma)


def dof_fraction(values: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """:func:`noise_confidence` from the prior's eigenvalues c (3M,) (:attr:`PriorEigen.values`,
    mm², so no eigendecomposition per call): ``mean_i c_i / (c_i + σ²)`` for each σ (…), mm."""
    c = np.asarray(values, np.float64)
    s2 = np.asarray(sigma, np.float64)[..., None] ** 2
    return (c / np.maximum(c + s2, 1e-300)).mean(axis=-1)


@dataclass(frozen=True)
class AdaptiveDenoiser:
    """The MAP denoiser of :class:`MarkerDenoiser` with σ estimated per request
    (``marker_noise_mm = "auto"``).

    Per call (one request: a frame, a batch or a whole performance) the per-frame noise
    σ̂_f is :func:`frame_noise`, the request's σ is their median (capture noise is a property
    of the capture, not of a frame; the median keeps a few frames far from the training span
    from raising it), floored at :data:`FILL_NOISE_MM` (so occluded markers are always
    completed by the prior), and the displacements are :class:`MarkerDenoiser`'s MAP
    estimate for that σ, by the prior's eigendecomposition (:class:`PriorEigen`: no inverse
    per request; two (3M)×(3M) products per frame with every marker).

    Attributes
    ----------
    prior : MarkerPrior
    energy : (M,M) float64      handle energy G of the thin shell (kept beside the prior)
    eigen : PriorEigen          the prior's eigendecomposition
    basis : (3M,k) float64      the prior's floor directions (:func:`floor_directions`)
    """

    prior: MarkerPrior
    energy: np.ndarray
    eigen: PriorEigen
    basis: np.ndarray

    @classmethod
    def build(cls, prior: MarkerPrior, energy: np.ndarray) -> "AdaptiveDenoiser":
        eigen = PriorEigen.of(prior)
        return cls(prior, np.asarray(energy, np.float64), eigen, eigen.floor_directions())

    #: visible markers are denoised (σ̂ > 0 in practice)
    interpolates = False

    def frame_noise(self, u: np.ndarray) -> np.ndarray:
        """σ̂ (F,) mm of head-aligned displacements u (F,M,3) (:func:`frame_noise`)."""
        return frame_noise(self.prior, u, self.basis, self.eigen)

    def request_noise(self, u: np.ndarray) -> float:
        """σ̂ (mm) of a request: the median of its frames' :meth:`frame_noise`."""
        u = np.asarray(u, np.float64)
        return float(np.median(self.frame_noise(u[None] if u.ndim == 2 else u)))

    def fixed(self, noise_mm: float) -> "FixedNoise":
        """The MAP denoiser of this prior for one request's σ = ``noise_mm`` (floored at
        :data:`FILL_NOISE_MM`)."""
        return FixedNoise(self.eigen, max(float(noise_mm), FILL_NOISE_MM), self.energy)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """MAP displacements for the request's σ̂, same shape as u (F,M,3) or (M,3), mm."""
        return self.fixed(self.request_noise(u))(u)


@dataclass(frozen=True)
class FixedNoise:
    """The MAP denoiser of a prior (:class:`PriorEigen`) at one request's estimated σ (mm):
    ``u (F,M,3) → x (F,M,3)`` (:meth:`PriorEigen.map`, then :func:`shell_completion` with the
    shell's handle energy (M,M))."""

    eigen: PriorEigen
    noise_mm: float
    energy: np.ndarray
    #: visible markers are denoised
    interpolates = False

    def __call__(self, u: np.ndarray) -> np.ndarray:
        u = np.asarray(u, np.float64)
        if u.ndim == 2:
            return self(u[None])[0]
        return shell_completion(self.energy, self.eigen, u, self.eigen.map(u, self.noise_mm))


def marker_denoiser(energy: np.ndarray, noise_mm: "float | str", prior_scale_mm: float,
                    prior: MarkerPrior | None = None) -> "MarkerDenoiser | ShellDenoiser | AdaptiveDenoiser":
    """The per-frame marker denoiser every marker-driven method uses (issue 17): a callable
    taking head-aligned marker displacements u (F,M,3) or (M,3), mm, NaN rows for occluded
    markers, to complete handle displacements of the same shape.

    * σ = ``noise_mm`` = 0: the papers' exact interpolation of the visible markers; occluded
      ones completed by the learned ``prior``'s conditional mean given them
      (:class:`PriorCompletion`), or, without a prior, by minimum energy (:class:`ShellDenoiser`,
      λ = 0);
    * σ > 0 with a learned ``prior``: its MAP estimate (:class:`MarkerDenoiser`, no shell term);
    * σ > 0 without one (a model saved before the learned prior existed): the shell prior's
      soft constraints, λ = σ²/τ² with τ = ``prior_scale_mm``
      (:func:`~service.geometry.thin_shell.marker_noise_ratio`, :class:`ShellDenoiser` with
      its precomputed operator);
    * σ = :data:`AUTO` (``"auto"``): σ estimated per request from the markers' residual
      against the learned prior (:class:`AdaptiveDenoiser`).

    Parameters
    ----------
    energy : (M,M) float      handle energy G of the thin shell (:func:`handle_energy_matrix`)
    noise_mm : float or "auto"   σ ≥ 0 per coordinate, mm
    prior_scale_mm : float    the shell prior's scale τ, mm (NaN allowed when σ = 0 or auto)
    prior : MarkerPrior, optional

    Raises
    ------
    ValueError   σ > 0 with a τ that is not finite and > 0; "auto" without a learned prior
    """
    if noise_mm == AUTO:
        if prior is None:
            raise ValueError('marker_noise_mm = "auto" needs a learned marker prior')
        return AdaptiveDenoiser.build(prior, energy)
    ratio = 0.0 if noise_mm == 0 else marker_noise_ratio(noise_mm, prior_scale_mm)
    if ratio == 0:
        return ShellDenoiser(energy, 0.0) if prior is None else PriorCompletion(np.asarray(energy, np.float64), prior)
    if prior is not None:
        return MarkerDenoiser.build(prior, energy, noise_mm, prior_scale_mm)
    return ShellDenoiser(energy, ratio, soft_handle_operator(energy, ratio))


__all__ = ["AUTO", "AdaptiveDenoiser", "FLOOR_FRACTION", "FixedNoise", "MarkerDenoiser", "MarkerPrior",
           "PriorCompletion", "PriorEigen", "SHELL_COMPLETION_RATIO", "SHELL_WEIGHT",
           "ShellDenoiser", "dof_fraction", "floor_directions", "frame_noise", "marker_denoiser",
           "noise_confidence", "shell_completion",
           "temporal_noise"]
