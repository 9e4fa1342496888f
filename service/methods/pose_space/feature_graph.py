"""The feature graph over the markers and its strain features (bickel2008 §3, §5.1).

The graph connects the H handle points by F edges "following approximately the contour of
the face, but without the need to produce a consistent mesh (edges may cross)". The pose
descriptor is the relative stretch of every edge,

    f_i = (‖p_i1 − p_i2‖ − l_i) / l_i,                                    (§5.1)

with l_i the rest length: invariant under rigid motion, 0 at rest.

The graph is given as marker-name pairs (:func:`graph_from_pairs`) or built automatically
(:func:`automatic_graph`): a Delaunay triangulation of the markers' UV positions (the face
unrolled, so the triangulation follows the surface), with two kinds of edges pruned:
edges whose rest length exceeds ``max_edge_ratio`` × the median (they jump across the mouth
corners, the UV chart borders or the eye openings), and edges that belong only to sliver
triangles (smallest UV angle below ``min_angle_deg``: the convex hull's fringe).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from service.methods.inputs import InvalidInput


@dataclass(frozen=True)
class FeatureGraph:
    """Edges between feature nodes and their rest lengths.

    edges : (E,2) int64          node indices (the markers, or a transferred model's nodes)
    rest_length : (E,) float64   l_i, actor unit (mm), > 0
    """

    edges: np.ndarray
    rest_length: np.ndarray

    @property
    def n_edges(self) -> int:
        return len(self.edges)

    def features(self, points: np.ndarray) -> np.ndarray:
        """Relative edge stretch f (…,E) of node positions (…,N,3) (§5.1)."""
        p = np.asarray(points, dtype=np.float64)
        d = p[..., self.edges[:, 0], :] - p[..., self.edges[:, 1], :]
        return (np.sqrt(np.einsum("...ed,...ed->...e", d, d)) - self.rest_length) / self.rest_length


def _rest_lengths(edges: np.ndarray, rest: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    bad = np.flatnonzero(~(length > 0))
    if len(bad):
        raise InvalidInput(f"feature edge {edges[bad[0]].tolist()} has zero rest length: its "
                           f"markers coincide on the neutral")
    return length


def automatic_graph(marker_uv: np.ndarray, rest: np.ndarray, max_edge_ratio: float = 2.5,
                    min_angle_deg: float = 12.0) -> FeatureGraph:
    """Feature graph from a Delaunay triangulation of the marker UVs (module docstring).

    Parameters
    ----------
    marker_uv : (M,2) float    marker texture coordinates
    rest : (M,3) float         marker positions on the neutral, mm
    max_edge_ratio : float     drop edges longer than this × the median rest length
    min_angle_deg : float      drop edges used only by UV triangles with a smaller angle

    Returns
    -------
    FeatureGraph with edges sorted (i < j, lexicographic)
    """
    uv = np.asarray(marker_uv, dtype=np.float64)
    rest = np.asarray(rest, dtype=np.float64)
    if len(uv) < 3:
        raise InvalidInput(f"an automatic feature graph needs at least 3 markers, got {len(uv)}")
    from scipy.spatial import Delaunay  # imported here: serve's start never needs it (issue 23's cold start)

    tri = Delaunay(uv).simplices                                            # (t,3)
    P = uv[tri]
    angles = []
    for k in range(3):
        a, b = P[:, (k + 1) % 3] - P[:, k], P[:, (k + 2) % 3] - P[:, k]
        cos = np.einsum("td,td->t", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    good = np.min(angles, axis=0) >= min_angle_deg                          # (t,)
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    keep = np.concatenate([good, good, good])
    key = e[:, 0] * len(uv) + e[:, 1]
    uniq, inv = np.unique(key, return_inverse=True)
    used_by_good = np.zeros(len(uniq), bool)
    np.logical_or.at(used_by_good, inv, keep)
    edges = np.stack([uniq // len(uv), uniq % len(uv)], axis=1)[used_by_good]
    length = _rest_lengths(edges, rest)
    short = length <= max_edge_ratio * np.median(length)
    return FeatureGraph(edges[short].astype(np.int64), length[short])


def graph_from_pairs(pairs: Sequence[tuple[str, str]], names: Sequence[str],
                     rest: np.ndarray) -> FeatureGraph:
    """Feature graph from marker-name pairs (the user's graph of §3).

    Raises :class:`InvalidInput` for an unknown name, a self-loop, or a repeated edge.
    """
    index = {n: i for i, n in enumerate(names)}
    edges = []
    for a, b in pairs:
        for n in (a, b):
            if n not in index:
                raise InvalidInput(f"feature edge ({a!r}, {b!r}): no marker named {n!r}")
        if a == b:
            raise InvalidInput(f"feature edge ({a!r}, {b!r}) connects a marker to itself")
        edges.append(sorted((index[a], index[b])))
    if not edges:
        raise InvalidInput("feature_edges is empty; give at least one marker-name pair or null")
    edges = np.asarray(edges, np.int64)
    if len(np.unique(edges, axis=0)) < len(edges):
        raise InvalidInput("feature_edges lists an edge twice")
    return FeatureGraph(edges, _rest_lengths(edges, np.asarray(rest, np.float64)))
