"""The committed stubs are exactly what ``python -m service.grpc.generate`` makes of the .proto."""

from __future__ import annotations

from pathlib import Path

from service.grpc import generate


def test_committed_stubs_match_a_fresh_generation(tmp_path):
    fresh = generate.generate(tmp_path)
    assert len(fresh) == 3 * len(generate.PROTOS)
    for path in fresh:
        committed = generate.PROTO_ROOT / path.relative_to(tmp_path)
        assert committed.read_bytes() == path.read_bytes(), (
            f"{committed} is stale: run `python -m service.grpc.generate` and commit the result")


def test_protoc_imports_become_package_relative():
    line = "from facesynth.v1 import synthesis_pb2 as facesynth_dot_v1_dot_synthesis__pb2\n"
    assert generate.relative_imports("import grpc\n" + line) == (
        "import grpc\nfrom . import synthesis_pb2 as facesynth_dot_v1_dot_synthesis__pb2\n")


def test_the_stubs_import_as_a_package_and_name_the_api_service():
    from service.grpc.facesynth.v1 import synthesis_pb2, synthesis_pb2_grpc

    service = synthesis_pb2.DESCRIPTOR.services_by_name["Synthesis"]
    assert service.full_name == "facesynth.v1.Synthesis"
    method = service.methods_by_name["StreamSynthesize"]
    assert (method.client_streaming, method.server_streaming) == (True, True)
    assert hasattr(synthesis_pb2_grpc, "SynthesisStub")
    assert Path(synthesis_pb2.__file__).parent == generate.PROTO_ROOT / "facesynth" / "v1"
