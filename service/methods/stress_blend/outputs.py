"""What a stress-blend model outputs: a module of its own so that the kind registry
(:mod:`service.methods.kinds`) names it without importing the model."""

#: outputs of :meth:`StressBlendModel.synthesize` (``mesh`` is the input mesh, passed through;
#: ``mesh_detailed`` the input mesh with the blended displacement baked in)
OUTPUTS = ("mesh", "mesh_detailed", "displacement", "albedo", "normal_map", "wrinkle_weights",
           "blend_weights")
DEFAULT_OUTPUTS = ("displacement", "albedo", "normal_map", "wrinkle_weights")
