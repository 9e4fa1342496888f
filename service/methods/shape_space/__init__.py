"""Shape-space performance enhancement (Bermano et al. 2014, "Facial performance enhancement
using dynamic shape space analysis", ACM TOG 33(2)): spatial detail transfer from a
high-resolution performance database (§4–5) and data-driven keyframe retiming (§6).

Modules: :mod:`.params` (parameters, constants), :mod:`.alignment` (head motion),
:mod:`.encoding` (frequency separation, rotation/stretch encoding), :mod:`.patches`
(seed-and-grow compression), :mod:`.regions` (voluntary regions and soft weights),
:mod:`.simplex_qp` (convex matching), :mod:`.blending` (eq. 4), :mod:`.temporal` (§6),
:mod:`.data` (the stored data), :mod:`.model` (train; the evaluator; enhance / retime),
:mod:`.store` (model directory).
"""

from service.methods.lazy import lazy_exports

# imported at first use (service.methods.lazy): the parameters are read without the model
__getattr__ = lazy_exports(__name__, {"ShapeSpaceData": "data", "ShapeSpaceEvaluator": "model",
                                      "ShapeSpaceModel": "model", "train": "model",
                                      "ShapeSpaceParams": "params"})
__all__ = ["ShapeSpaceData", "ShapeSpaceEvaluator", "ShapeSpaceModel", "ShapeSpaceParams", "train"]
