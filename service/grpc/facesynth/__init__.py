"""Generated protobuf packages (``facesynth.v1``); see :mod:`service.grpc.generate`."""
