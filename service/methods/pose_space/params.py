"""Training parameters of pose-space detail (bickel2008 §5): one frozen pydantic model per method.

:class:`PsdParams` (kind ``psd``, §5.2: one feature distance per example pose) and
:class:`WpsdParams` (kind ``wpsd``, §5.3: per-vertex weighted feature distances) share
:class:`PoseSpaceParams`; the field ``method`` tells them apart in a stored manifest
(:func:`parse_params`). The library, the API and OpenAPI use these same models.
"""

from __future__ import annotations

from typing import Literal, Union

from pydantic import Field, model_validator

from service.methods.params import MarkerParams

#: relative ridge always added to least-squares normal equations (x mean diagonal): keeps
#: nearly dependent basis columns solvable; changes well-posed fits by ~1e-10 relative
RIDGE_FLOOR = 1e-10
#: candidate smoothing values of the validation (relative ridge, see ``rbf.solve_weights``)
SMOOTHING_GRID = (0.0, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2, 3e-2, 1e-1)
#: seed of the validation's marker noise
VALIDATION_SEED = 0
#: seed of the noisy copies of the training frames (``noise_copies``)
NOISE_COPIES_SEED = 1
#: the marker regression to opt in with: s (median marker spacings) and ridge λ (the field's
#: default), chosen on sample family a, confirmed on family b (benchmarks/generalization_report.py,
#: level 0, 6 frames a row, every range × clean / noisy / occluded markers; README "Pose-space
#: detail"). Off by default: at level 1 the full sparse form cost 5× the frame time (README);
#: the low-rank form it is kept in now has not been timed for pose space
RECOMMENDED_MARKER_REGRESSION = 3.0
MARKER_REGRESSION_RIDGE = 0.1


def _marker_regression(default: float | None, which: str):
    """The ``marker_regression`` field, declared once for both methods; ``default`` and the
    sentence ``which`` that says why differ (PSD: none; WPSD: issue 17, :class:`WpsdParams`)."""
    return Field(
        default=default, gt=0.0, le=20.0,
        description="Learn the part of the corrections that is linear in the markers' "
                    "displacement vectors first (marker_regression.py: per vertex a ridge "
                    "regression on the markers, weighted by exp(−d²/s²) of their rest distance "
                    "d), and the RBFs on what it leaves; the value is s in median nearest-marker "
                    "spacings of the actor; null: none, bickel2008 as printed. The regression is "
                    f"not faded by the confidence. {which}")


class PoseSpaceParams(MarkerParams):
    """Parameters shared by PSD and WPSD (bickel2008 §5.1-5.2)."""

    fit: Literal["least_squares", "exact"] = Field(
        default="least_squares",
        description="How the RBF weights are computed from the selected basis poses (§5.2): "
                    "'exact' interpolates the P basis poses, 'least_squares' fits all T "
                    "training frames with the P basis poses as centres.")
    basis_size: int = Field(
        default=12, ge=1, le=64,
        description="Largest number P of basis poses chosen by the greedy selection (§5.2: "
                    "start from the rest pose, add the worst-fit training frame).")
    error_threshold: float = Field(
        default=0.0, ge=0.0, lt=1.0,
        description="Stop the greedy selection once the relative RMS training error of the "
                    "corrections falls to this value (0: always use basis_size poses).")
    smoothing: float | None = Field(
        default=None, ge=0.0, le=10.0,
        description="Relative ridge λ of the RBF solve ((ΦᵀΦ + λ·tr(ΦᵀΦ)/P·I) w = Φᵀd). "
                    "null: chosen from smoothing_grid by validation on held-out training "
                    "frames (every validation_stride-th frame, markers with "
                    "validation_noise_mm noise).")
    smoothing_grid: tuple[float, ...] = Field(
        default=SMOOTHING_GRID, min_length=1,
        description="Candidate values of the validation of smoothing.")
    validation_stride: int = Field(
        default=4, ge=2, le=100,
        description="Every k-th training frame is held out when smoothing is validated.")
    validation_noise_mm: float = Field(
        default=0.3, ge=0.0, le=10.0,
        description="Gaussian noise (σ per coordinate, actor unit) added to the held-out "
                    "frames' markers when smoothing is validated: the tracking noise the "
                    "detail must be robust to (a property of the capture system; 0 validates "
                    "on clean markers).")
    feature_edges: tuple[tuple[str, str], ...] | None = Field(
        default=None,
        description="The feature graph as marker-name pairs (§3); null builds it "
                    "automatically (Delaunay triangulation of the markers in UV, long and "
                    "sliver-only edges pruned).")
    max_edge_ratio: float = Field(
        default=2.5, gt=1.0, le=100.0,
        description="Automatic graph: drop edges longer (rest length) than this multiple "
                    "of the median edge.")
    min_angle_deg: float = Field(
        default=12.0, ge=0.0, lt=60.0,
        description="Automatic graph: drop edges that belong only to UV triangles with a "
                    "smaller angle (boundary slivers of the triangulation).")
    map_resolution: int | None = Field(
        default=None, ge=16, le=8192,
        description="Texels per side of the fine displacement map learned from the "
                    "training clips' maps (null: the clips' own size).")
    extrapolation_margin: float | None = Field(
        default=0.25, ge=0.0,
        description="With clamp, each feature (edge strain) is limited to its training "
                    "range widened by this fraction of the range on both sides, so poses "
                    "beyond the training data do not extrapolate the linear kernel without "
                    "bound; null disables the limit.")
    confidence_fade: bool = Field(
        default=True,
        description="Synthesis fades every frame's pose-space vertex corrections toward "
                    "the thin shell by the frame's range confidence exp(−δ/δ₀) (δ the features' "
                    "distance outside the training range, δ₀ the training frames' median "
                    "feature norm), so a pose far outside the training detail tends to the "
                    "shell (the fine map is kept); false only reports the confidence.")
    noise_copies: int = Field(
        default=0, ge=0, le=8,
        description="Least squares: the fit also sees this many copies of every training "
                    "frame whose features come from its markers plus Gaussian noise of "
                    "validation_noise_mm (seeded), with the frame's own targets — training with "
                    "noise, so the weights (RBF and polynomial) do not pass marker noise into the "
                    "detail; 0 fits the clean features only. The smoothing validation fits with "
                    "the same copies.")
    marker_completion: Literal["shell", "training"] = Field(
        default="shell",
        description="Occluded markers (NaN): 'shell' completes them by the thin shell's "
                    "minimum energy; 'training' predicts them from the visible ones with the "
                    "training frames' marker statistics (a Gaussian of the aligned marker "
                    "displacements, observation noise validation_noise_mm: the MAP of the "
                    "missing markers) before the shell, so the shell and the features at them "
                    "follow the expression. A transferred model (other markers) uses 'shell'.")
    marker_prior: Literal["none", "posterior"] = Field(
        default="posterior",
        description="'posterior' replaces the markers (visible and occluded) by their posterior "
                    "mean under the training markers' Gaussian (mean + principal modes) plus an "
                    "off-mode part whose per-marker variance is estimated by leaving one training "
                    "clip out, with observation noise validation_noise_mm: a Wiener filter that "
                    "keeps what the training explains, shrinks the rest by its signal-to-noise "
                    "ratio, and completes occluded markers by the modes plus the thin shell's "
                    "minimum-energy completion of the residual (model.marker_posterior); it "
                    "supersedes marker_completion. 'none': the markers as given.")
    posterior_noise: Literal["validation", "frame"] = Field(
        default="validation",
        description="Observation noise σ of marker_prior = 'posterior': 'validation' uses "
                    "validation_noise_mm for every frame; 'frame' each frame's own estimate σ̂ "
                    "(the median deviation of its markers in the directions the training never "
                    "moved, the confidence's noise estimate) clipped to [0.01 mm, "
                    "validation_noise_mm], so clean markers of an expression the training did "
                    "not show are shrunk less toward the training's modes, and no frame more "
                    "than with 'validation'. A transferred model (no learned marker prior of its "
                    "own) uses 'validation'.")
    occlusion: Literal["shell", "reweight"] = Field(
        default="shell",
        description="Features of edges at occluded markers: 'shell' uses them as the thin "
                    "shell's minimum-energy completion gives them; 'reweight' weights every "
                    "edge's term of the feature distance by its visibility (the share of its "
                    "nodes' shell displacement carried by visible markers) and renormalizes "
                    "α per vertex (eq. 3), so filled strains count less.")
    marker_regression: float | None = _marker_regression(None, "Default null.")
    marker_regression_ridge: float = Field(
        default=MARKER_REGRESSION_RIDGE, gt=0.0, le=10.0,
        description="Relative ridge λ of the marker regression (× the mean diagonal of each "
                    "vertex's kernel).")
    selection_vertices: int = Field(
        default=4096, ge=16,
        description="Vertices (an even stride over the mesh) on which WPSD's greedy basis "
                    "selection and the smoothing validation measure the fit error.")

    @model_validator(mode="after")
    def _auto_noise_needs_markers_as_given(self):
        # the posterior splits the markers into two parts denoised apart: a σ estimated per
        # request would be estimated twice, on neither part's noise
        if self.marker_noise_mm == "auto" and self.marker_prior == "posterior":
            raise ValueError('marker_noise_mm = "auto" needs marker_prior = "none" (the posterior '
                             'already filters the markers with validation_noise_mm)')
        return self


class PsdParams(PoseSpaceParams):
    """Pose-space deformation with one feature distance per pose (bickel2008 §5.2, eq. 2)."""

    method: Literal["psd"] = Field(default="psd", description="Global pose-space deformation.")
    polynomial: Literal["none", "linear"] = Field(
        default="none",
        description="Polynomial term of the biharmonic RBF ([CBC*01]; polynomial.py): 'none' "
                    "is eq. 2 as printed; 'linear' adds a constant and a linear term in all E "
                    "features (E + 1 unknowns per coordinate: with fewer training frames than "
                    "features it interpolates the training set).")


class WpsdParams(PoseSpaceParams):
    """Weighted pose-space deformation (bickel2008 §5.3, eq. 3-5).

    Notes
    -----
    ``marker_regression`` is on by default (s = 3 median marker spacings, λ = 0.1; issue 17).
    On the generalization report's held-out performances (level 0, 8 frames each, both
    sample families × in range / combinations / out of range × clean / noisy / occluded
    markers) WPSD with it has a lower mean and max face vertex error, a lower detail rel err
    and a higher detail correlation than without on all 18 rows (e.g. a in range clean 0.198
    / 2.21 mm / 0.53 → 0.155 / 1.72 / 0.39, b combinations clean 0.295 / 5.39 / 0.91 → 0.163 /
    2.25 / 0.65). Its cost was why it was off: measured when the regression was one sparse
    product per frame, level 1 `mesh` went 12.5 → 62 ms. Kept low-rank with int16 rows since
    (:class:`~service.geometry.marker_regression.MarkerRegression`), level 1 (44,786
    vertices, 160 training frames; ``pose_space_report.py --speed-only``, load 1.0, 1
    thread): ``mesh`` 11.8 → 11.2 ms a frame, ``mesh`` + ``displacement`` 58.8 → 48.0 ms,
    training 87 → 106 s, the model 194 → 246 MB. The price: the confidence ranks the error
    less well out of range (Spearman ρ a 0.89 → 0.65, b 0.75 → 0.74; issue 17 asks ≥ 0.6).
    ``marker_regression: null`` is bickel2008 as printed.
    """

    method: Literal["wpsd"] = Field(default="wpsd", description="Per-vertex weighted PSD.")
    marker_regression: float | None = _marker_regression(
        RECOMMENDED_MARKER_REGRESSION,
        f"Default {RECOMMENDED_MARKER_REGRESSION:g} (issue 17): better than none on every "
        "metric of every held-out row of both sample families, at about the same frame time.")
    polynomial: Literal["none", "linear"] = Field(
        default="linear",
        description="Polynomial term of the biharmonic RBF ([CBC*01]; polynomial.py): "
                    "'linear' adds per vertex a constant and a linear term in the features of "
                    "the vertex's α support (local, like the distance); 'none' is eq. 5 as "
                    "printed.")
    alpha_threshold: float = Field(
        default=0.025, gt=0.0, lt=1.0,
        description="Discard edge weights ᾱ below this value (§5.3: 0.025).")
    max_edges_per_vertex: int = Field(
        default=16, ge=1, le=256,
        description="At most this many feature edges influence a vertex (§5.3: 16).")
    beta: float | None = Field(
        default=None, gt=0.0,
        description="Decay β of eq. 4 in 1/actor unit; null: per vertex, from the local "
                    "density of the graph, so that exactly max_edges_per_vertex edges have "
                    "ᾱ ≥ alpha_threshold.")


Params = Union[PsdParams, WpsdParams]


def parse_params(raw: dict) -> Params:
    """The params model of a stored manifest's ``params`` (by its ``method``)."""
    cls = WpsdParams if raw.get("method", "wpsd") == "wpsd" else PsdParams
    return cls.model_validate(raw)
