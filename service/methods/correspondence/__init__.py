"""Facial scan correspondence in UV space (Vuvuzela; digital_ira_course2014, "Vuvuzela: A
Facial Scan Correspondence Tool", Ichikari, Alexander, Debevec).

Modules: :mod:`.params` (the one parameter model), :mod:`.prewarp` (Delaunay
piecewise-affine pre-warp, step 1), :mod:`.texture` (over-sharpened flow textures,
occlusion masks, pinned dots), :mod:`.correspond` (the three
steps: pre-warp, dense flow, composed warp of every map), :mod:`.blendshapes` (artist-mesh
blendshapes and artist-UV maps), :mod:`.accuracy` (error against a known correspondence).
"""

from service.methods.lazy import lazy_exports

# imported at first use (service.methods.lazy): the parameters are read without the method
# and OpenCV
__getattr__ = lazy_exports(__name__, {"CorrespondenceParams": "params",
                                      "CorrespondenceResult": "correspond",
                                      "correspond": "correspond",
                                      "blendshape_vertices": "blendshapes",
                                      "to_artist_uv": "blendshapes"})

__all__ = ["CorrespondenceParams", "CorrespondenceResult", "blendshape_vertices", "correspond",
           "to_artist_uv"]
