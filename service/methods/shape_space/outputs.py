"""What a shape-space model outputs: a module of its own so that the kind registry
(:mod:`service.methods.kinds`) names it without importing the model."""

#: outputs of :meth:`ShapeSpaceModel.enhance`: every output of the service
#: (:data:`service.methods.outputs.OUTPUTS`) and per-vertex ``colors``
OUTPUTS = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map", "colors")
