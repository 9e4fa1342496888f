"""Compression of a mesh animation to a linear-blend-skinned bone rig (the "Game Rig" of
the Digital Ira course, 2014: "a bone weight and transform solver [that] optimizes the
smooth skinning weights and the bone animated transforms"), by Smooth Skinning
Decomposition with Rigid Bones (Le & Deng 2012, ACM TOG 31(6) 199, "SSDR").

Modules: :mod:`.params` (the one parameter model), :mod:`.skinning` (linear blend
skinning, eq. 1), :mod:`.clustering` (the rigid-bone initialization, §4.1),
:mod:`.transforms` (the bone update, §3.2), :mod:`.weights` (the weight update, §3.3),
:mod:`.decomposition` (the alternating solve), :mod:`.rig` (the result, NPZ and glTF
export).
"""
