"""gRPC real-time path (API.md): the ``facesynth.v1`` proto, its generated stubs, the
streaming server and a small client helper."""
