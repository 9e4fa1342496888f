"""Facial scan correspondence in UV space (Vuvuzela; digital_ira_course2014, "Vuvuzela: A
Facial Scan Correspondence Tool", Ichikari, Alexander, Debevec).

Modules: :mod:`.prewarp` (Delaunay piecewise-affine pre-warp, step 1), :mod:`.texture`
(over-sharpened flow textures, occlusion masks, pinned dots), :mod:`.correspond` (the three
steps: pre-warp, dense flow, composed warp of every map), :mod:`.blendshapes` (artist-mesh
blendshapes and artist-UV maps), :mod:`.accuracy` (error against a known correspondence).
"""

from service.methods.correspondence.blendshapes import blendshape_vertices, to_artist_uv
from service.methods.correspondence.correspond import (
                                                       CorrespondenceParams,
                                                       CorrespondenceResult,
                                                       correspond,
)

__all__ = ["CorrespondenceParams", "CorrespondenceResult", "blendshape_vertices", "correspond",
           "to_artist_uv"]
