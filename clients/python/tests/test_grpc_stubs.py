"""The SDK's gRPC stubs (facesynth_client/_proto) are exactly what the generator makes of the
server's synthesis.proto, and they describe the same service as the server's stubs."""

from __future__ import annotations

import pytest

pytest.importorskip("grpc_tools")

from service.grpc import generate  # noqa: E402  (the generator lives with the .proto)


def test_the_sdk_stubs_match_a_fresh_generation_of_the_proto(tmp_path):
    fresh = generate.generate(tmp_path)
    assert len(fresh) == 3 * len(generate.PROTOS)
    for path in fresh:
        committed = generate.SDK_STUBS_ROOT / path.relative_to(tmp_path)
        assert committed.read_bytes() == path.read_bytes(), (
            f"{committed} is stale: run `python -m service.grpc.generate` and commit the result")


def test_the_sdk_stubs_are_the_sdk_package_and_describe_the_servers_service():
    from facesynth_client._proto.facesynth.v1 import synthesis_pb2 as sdk
    from service.grpc.facesynth.v1 import synthesis_pb2 as server

    assert sdk.__name__.startswith("facesynth_client.")
    assert sdk.DESCRIPTOR.serialized_pb == server.DESCRIPTOR.serialized_pb
    method = sdk.DESCRIPTOR.services_by_name["Synthesis"].methods_by_name["StreamSynthesize"]
    assert (method.client_streaming, method.server_streaming) == (True, True)


def test_the_generator_writes_both_copies_by_default():
    assert generate.STUB_ROOTS == (generate.PROTO_ROOT, generate.SDK_STUBS_ROOT)
    assert generate.SDK_STUBS_ROOT.is_dir()
