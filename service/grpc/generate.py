"""Generate the Python stubs of the gRPC API from its ``.proto``, reproducibly.

Run ``python -m service.grpc.generate`` after editing
``service/grpc/facesynth/v1/synthesis.proto`` and commit the regenerated files, written in two
places from the one ``.proto``: beside it for the server, and into the client SDK (which never
imports the server) for its streaming client::

    service/grpc/facesynth/v1/synthesis_pb2.py        messages
    service/grpc/facesynth/v1/synthesis_pb2.pyi       their type stubs
    service/grpc/facesynth/v1/synthesis_pb2_grpc.py   service stub and servicer base
    clients/python/src/facesynth_client/_proto/facesynth/v1/synthesis_pb2{.py,.pyi,_grpc.py}

``grpc_tools.protoc`` runs with fixed arguments (include root ``service/grpc``, so the
proto registers as ``facesynth/v1/synthesis.proto`` in the descriptor pool) and the
absolute import protoc writes into ``*_pb2_grpc.py`` (``from facesynth.v1 import
synthesis_pb2``, which only works with ``service/grpc`` on ``sys.path``) is rewritten to a
package-relative one, so the stubs import as ``service.grpc.facesynth.v1.synthesis_pb2`` (and
``facesynth_client._proto.facesynth.v1.synthesis_pb2``). Both copies register the same file
``facesynth/v1/synthesis.proto`` with the same bytes, so a process may import both.

The output depends on the generator's version (it writes the protobuf and grpcio
versions it requires at run time into the stubs), so the generator is pinned:
:data:`GRPC_TOOLS_VERSION`, the same pin as the ``dev`` extra in ``pyproject.toml``.
``tests/grpc/test_generate.py`` and ``clients/python/tests/test_grpc_stubs.py`` regenerate into
a temporary directory and compare bytes with each copy.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import re
import sys
from pathlib import Path

#: the grpcio-tools release that generated the committed stubs (pyproject.toml's dev extra)
GRPC_TOOLS_VERSION = "1.76.0"
#: protoc's include root, and the proto files relative to it
PROTO_ROOT = Path(__file__).resolve().parent
PROTOS = ("facesynth/v1/synthesis.proto",)
#: the SDK's copy of the stubs (its package ``facesynth_client._proto``)
SDK_STUBS_ROOT = (PROTO_ROOT.parents[1] / "clients" / "python" / "src" / "facesynth_client"
                  / "_proto")
#: every place the committed stubs live
STUB_ROOTS = (PROTO_ROOT, SDK_STUBS_ROOT)
#: protoc's absolute import of a sibling module: ``from facesynth.v1 import x_pb2 as ...``
_ABSOLUTE_IMPORT = re.compile(r"^from facesynth\.v1 import (\w+_pb2) as ", re.MULTILINE)


def protoc_arguments(out_dir: Path) -> list[str]:
    """The fixed ``protoc`` command line writing the stubs of :data:`PROTOS` under ``out_dir``."""
    return ["grpc_tools.protoc", f"-I{PROTO_ROOT}", f"--python_out={out_dir}",
            f"--pyi_out={out_dir}", f"--grpc_python_out={out_dir}", *PROTOS]


def relative_imports(source: str) -> str:
    """``source`` with protoc's absolute imports of sibling stubs made package-relative."""
    return _ABSOLUTE_IMPORT.sub(r"from . import \1 as ", source)


def generate(out_dir: str | Path = PROTO_ROOT) -> list[Path]:
    """Write the stubs under ``out_dir`` (default: beside the protos) and return their paths.

    Raises
    ------
    RuntimeError
        if the installed grpcio-tools is not :data:`GRPC_TOOLS_VERSION` (its output would
        differ from the committed stubs), or protoc fails.
    """
    installed = importlib.metadata.version("grpcio-tools")
    if installed != GRPC_TOOLS_VERSION:
        raise RuntimeError(f"the stubs are generated with grpcio-tools=={GRPC_TOOLS_VERSION}, "
                           f"found {installed}: pip install 'grpcio-tools=={GRPC_TOOLS_VERSION}'")
    from grpc_tools import protoc

    out_dir = Path(out_dir)
    if protoc.main(protoc_arguments(out_dir)) != 0:
        raise RuntimeError(f"protoc failed on {', '.join(PROTOS)}")
    paths = []
    for proto in PROTOS:
        stem = out_dir / proto.removesuffix(".proto")
        for suffix in ("_pb2.py", "_pb2.pyi", "_pb2_grpc.py"):
            path = stem.with_name(stem.name + suffix)
            path.write_text(relative_imports(path.read_text()))
            paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.grpc.generate",
                                     description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, action="append",
                        help="root to write the stubs under (repeatable; default: beside the "
                             ".proto files and into the client SDK)")
    args = parser.parse_args(argv)
    for root in args.out or STUB_ROOTS:
        for path in generate(root):
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
