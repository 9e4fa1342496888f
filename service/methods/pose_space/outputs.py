"""What a pose-space model (psd, wpsd) outputs: a module of its own so that the kind
registry (:mod:`service.methods.kinds`) names it without importing the model."""

#: outputs of :meth:`PoseSpaceModel.synthesize` (API.md; the PDM's vocabulary without albedo)
OUTPUTS = ("mesh", "mesh_detailed", "displacement", "normal_map")
