"""Generated gRPC stubs of facesynth/v1/synthesis.proto (``python -m service.grpc.generate``;
the .proto is service/grpc/facesynth/v1/synthesis.proto in the repository). Do not edit."""
