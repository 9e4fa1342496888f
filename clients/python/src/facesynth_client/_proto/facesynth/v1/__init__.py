"""``facesynth.v1``: the stubs generated from ``synthesis.proto`` (do not edit them)."""
