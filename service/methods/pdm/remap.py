"""Novel marker placement: drive a trained PDM model with a different marker set (ma2008 §5).

"the new motion capture markers (observed in a neutral position) must be mapped onto the
neutral mesh acquired during training. Second, if the density of motion capture markers
is different, it will be important to scale the values E^u(t) and E^v(t) accordingly."

1. :func:`register_markers`: the new markers, observed in a neutral pose in their own
   capture space, are rigidly registered to the training neutral (ICP: closest surface
   points, weighted Kabsch, repeat) and snapped onto it as (triangle, barycentric).
2. :func:`remap_model`: the model is rebuilt around the new markers: their coarse mesh,
   thin-shell handles and basis; the PDM domain axes q̂, r̂ and the head-pose weights
   interpolated from the training markers' at the new markers' texture coordinates (the
   axes re-orthonormalized); and the strain scale rescaled for the new density: eq. 2's
   absolute strain grows with the neighbourhood's extent, so a new marker's E is multiplied
   by σ_ref(training) / σ_ref(new), the ratio of the rest standard deviations of the two
   neighbourhoods there, before the training √|N2| scale. The coefficient maps, the
   extrapolation limits and the validity regions live in texture space and are kept as
   they are (regrouped by the new coarse elements).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from service.geometry.closest_point import closest_points
from service.geometry.rigid import RigidTransform, rigid_align
from service.methods.inputs import ActorData, InvalidInput
from service.methods.pdm.base_surface import BaseSurface, handle_vertices
from service.methods.pdm.data import PdmDerived
from service.methods.pdm.deformation import DeformationAxes, barycentric_operator, marker_mesh
from service.methods.pdm.model import PdmEvaluator, PdmModel, element_field, marker_axes

#: ICP stops when the RMS distance changes by less than this (actor units)
ICP_TOL = 1e-6
ICP_ITERATIONS = 300


@dataclass(frozen=True)
class MarkerRegistration:
    """New markers on the training neutral.

    transform : RigidTransform   capture space → training neutral
    triangle : (M,) int;  barycentric : (M,3)   the snapped surface points
    distance : (M,) float        distance of each registered marker from the surface
    """

    transform: RigidTransform
    triangle: np.ndarray
    barycentric: np.ndarray
    distance: np.ndarray


def register_markers(V: np.ndarray, F: np.ndarray, P: np.ndarray,
                     iterations: int = ICP_ITERATIONS) -> MarkerRegistration:
    """Rigid ICP of neutral markers P (M,3) onto the surface (V (n,3), F (m,3)), then snap.

    Starts from the identity (the new session's capture space roughly agrees with the
    training one, as with a repeated mocap setup); each step aligns the markers to their
    closest surface points (Kabsch).
    """
    P = np.asarray(P, dtype=np.float64)
    T = RigidTransform(np.eye(3), np.zeros(3))
    previous = np.inf
    for _ in range(iterations):
        X = T.apply(P)
        cp = closest_points(V, F, X)
        rms = float(np.sqrt(np.mean(cp.distance ** 2)))
        if previous - rms < ICP_TOL:
            break
        previous = rms
        T = rigid_align(P, cp.point)
    cp = closest_points(V, F, T.apply(P))
    return MarkerRegistration(T, cp.triangle, cp.barycentric, cp.distance)


def remap_model(model: PdmModel, triangle: np.ndarray, barycentric: np.ndarray,
                names: tuple[str, ...] | None = None) -> PdmModel:
    """The model driven by a new marker layout (triangle (M',), barycentric (M',3) on the neutral).

    Returns a new :class:`PdmModel` whose :meth:`~PdmModel.synthesize` takes (F,M',3)
    markers of the new layout. Raises :class:`InvalidInput` for layouts whose markers share
    a thin-shell handle.
    """
    d, ev = model.data, model.evaluator
    F = d.faces
    triangle = np.asarray(triangle, np.int64)
    barycentric = np.asarray(barycentric, np.float64)
    names = names or tuple(f"M{i:03d}" for i in range(len(triangle)))
    actor = ActorData(model.neutral(), F, d.uv, d.uv_faces, triangle, barycentric, names)
    rest = actor.marker_positions()
    try:
        handles = handle_vertices(F, triangle, barycentric, names)
    except ValueError as e:
        raise InvalidInput(str(e)) from None
    mesh = marker_mesh(actor.marker_uv(), rest, marker_axes(actor))

    # training quantities at the new markers, through the training coarse mesh
    W = barycentric_operator(d.mesh, mesh.uv)                              # (M',M)
    old = d.mesh
    q = W @ d.axes.q
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = W @ d.axes.r
    r -= np.sum(r * q, axis=1, keepdims=True) * q
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    scale = np.ones((len(triangle), 5))
    density = (W @ old.rest_sigma) / np.maximum(mesh.rest_sigma, 1e-12)      # σ_train / σ_new
    scale[:, 3:] = np.sqrt(W @ old.n2_sizes)[:, None] * density
    axes = DeformationAxes(q, r, scale, W @ d.axes.energy, 0, float("nan"))

    base = BaseSurface.from_smooth(d.smooth, F, d.uv, d.uv_faces, handles, rest)
    data = replace(d, handles=handles, rest_markers=rest, mesh=mesh, axes=axes, pose_weights=W @ d.pose_weights,
                   metrics={**d.metrics, "remapped_markers": len(triangle)},
                   validity=ev.validity_data())      # a model stored without them: the derived ones
    # same texels, same coefficients, limits and validity regions (stored in texel order);
    # only the parameter fields (and so the texels' grouping by coarse element) change
    orders = {name: np.arange(len(d.uv)) if name == "vertex" else
              element_field(mesh, axes, getattr(d, name).index, getattr(d, name).resolution)[0]
              for name in ev.orders}

    def regroup(name: str, values: np.ndarray) -> np.ndarray:      # (…,P) old order → new order
        stored = np.empty_like(values)
        stored[..., ev.orders[name]] = values
        return stored[..., orders[name]]

    derived = PdmDerived(limits={k: regroup(k, b.limit) for k, b in ev.bands.items()})
    return PdmModel(data, PdmEvaluator.build(data, base, derived))
