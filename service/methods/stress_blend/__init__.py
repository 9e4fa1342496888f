"""Stress-driven blending of expression maps (the "Real-Time Rendering" of the Digital Ira
course, 2014: "surface stress values [are used] to blend diffuse texture, specular, normal,
and displacement maps from the different high-resolution expression scans per-vertex at
run time"), with the per-region wrinkle-map weights a real-time engine plays back.

Modules: :mod:`.params` (the one parameter model), :mod:`service.geometry.surface_strain`
(per-vertex surface stress from deformation gradients), :mod:`.weights` (stress similarity → blend weights),
:mod:`.regions` (wrinkle masks and per-frame region weights), :mod:`.data` (the stored
data), :mod:`.model` (training, the evaluator, synthesis), :mod:`.store` (model directories).
"""
