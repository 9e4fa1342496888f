"""Where motion-capture markers sit on a mesh: the marker layout (API.md ``PUT /markers``).

The layout is read from JSON by :func:`service.io.marker_json.read_marker_layout` and resolved
to surface points by :func:`service.geometry.closest_point.resolve_marker_layout`; both take
the type and the tolerance from here, so they are declared once, below both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BARYCENTRIC_TOLERANCE = 1e-4
"""How far the barycentric coordinates of a layout marker may sum from 1 (and fall below 0).

Layouts exported with 6 decimals sum to 1 ± 1e-6 and more (three rounded thirds are off by
1e-6; a coordinate rounded from 0.9999995 by 5e-7 each); 1e-4 accepts every such file while
still refusing coordinates that are really wrong (a marker 1e-4 of a triangle away is
sub-micron on a face). Accepted coordinates are clipped at 0 and renormalized to sum to 1
(:func:`service.geometry.closest_point.resolve_marker_layout`), and the API reports how many
markers were."""


@dataclass(frozen=True, eq=False)
class MarkerLayout:
    """Where the markers sit on the actor's neutral (API.md ``PUT /markers``).

    Each marker is given one way: on a vertex, at barycentric coordinates in a triangle, or as a
    free position (to be snapped to the surface by the caller; kept as given here).

    Attributes
    ----------
    names : tuple of M str          unique marker names, in layout order
    kinds : tuple of M str          ``"vertex"``, ``"triangle"`` or ``"position"`` per marker
    vertex : (M,) int64             vertex index, -1 where the kind is not ``vertex``
    triangle : (M,) int64           triangle index, -1 where the kind is not ``triangle``
    barycentric : (M,3) float64     non-negative, summing to 1; NaN where not ``triangle``
    position : (M,3) float64        in the actor's unit; NaN where not ``position``
    """

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    vertex: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray
    position: np.ndarray
