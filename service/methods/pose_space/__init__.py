"""Pose-space animation and transfer of facial details (Bickel, Lang, Botsch, Otaduy, Gross
2008, "Pose-space animation and transfer of facial details", SCA).

Modules: :mod:`.params` (PsdParams / WpsdParams), :mod:`.feature_graph` (§3, §5.1 the graph
and its strain features), :mod:`.corrections` (§4 large scale, §5.2 corrections in tangent
frames), :mod:`.rbf` (§5.2 exact / least-squares RBF weights, greedy basis),
:mod:`.weighting` (§5.3 eq. 3-4, sparse α), :mod:`.model` (train, the stored data, the
evaluator, synthesis), :mod:`.correction_sum` and :mod:`service.geometry.shell_frames` (the compiled
per-frame evaluation of eq. 3/5 and of the shell with its rotated corrections),
:mod:`.store` (model directory), :mod:`.transfer` (§5.4).
"""

from service.methods.lazy import lazy_exports

# imported at first use (service.methods.lazy): the parameters are read without the model
__getattr__ = lazy_exports(__name__, {"PoseSpaceData": "model", "PoseSpaceModel": "model",
                                      "train": "model", "PoseSpaceParams": "params",
                                      "PsdParams": "params", "WpsdParams": "params"})
__all__ = ["PoseSpaceData", "PoseSpaceModel", "PoseSpaceParams", "PsdParams", "WpsdParams", "train"]
