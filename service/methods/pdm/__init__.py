"""Deformation-driven polynomial displacement maps (Ma et al. 2008, "Facial performance
synthesis using deformation-driven polynomial displacement maps", SIGGRAPH Asia).

Modules: :mod:`.deformation` (§4.1, the marker-space parameters d1, d2),
:mod:`.polynomial` (§4.2, per-texel regularized polynomial fitting).

Patent notice: the PDM method is covered by US patent 8,902,232 B2 (University of Southern
California, in force until about 2031). Commercial users should check licensing.
"""
