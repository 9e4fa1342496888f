"""Generated protobuf packages (``facesynth.v1``)."""
