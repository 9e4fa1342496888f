"""What ``facesynth serve`` imports before it serves (issue 23's cold start): no OpenCV, no
Numba and no method's model module but the one a model load asks for."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: the modules cmd_serve imports before uvicorn runs (service/cli.py)
SERVE_IMPORTS = """
import json, sys
from service.app.threads import apply_blas_threads
from service.config import Settings
from service.jobs.queue_storage import queue_storage, worker_storage
from service.logs import configure_logging
from service.app.services import Services
from service.grpc.server import is_loopback, serve
from service.jobs.job_threads import JobThreads
import uvicorn
from service.api.app import create_app
from service.api.connections import protocol_class
from service.methods.kinds import KINDS
before = set(sys.modules)
KINDS["stress_blend"].load      # reading a kind imports nothing
after = set(sys.modules)
print(json.dumps({"modules": sorted(before), "added": sorted(after - before)}))
"""

#: imported only where they run: OpenCV (optical flow, video decoding), Numba (the
#: compiled kernels of a loaded model) and the model modules of the kinds
NOT_AT_START = ("cv2", "numba", "service.geometry.optical_flow",
                "service.methods.correspondence.correspond", "service.methods.pdm.model",
                "service.methods.shape_space.model", "service.methods.stress_blend.model",
                "service.geometry.half_kernel")


def _imported(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_serve_start_imports_no_opencv_numba_or_model_modules():
    seen = _imported(SERVE_IMPORTS)
    assert [m for m in NOT_AT_START if m in seen["modules"]] == []
    assert seen["added"] == []


def test_a_kinds_load_imports_its_model_module_at_the_first_call():
    seen = _imported("""
import json, sys
from service.methods.kinds import get_kind
from service.methods.lazy import resolve
kind = get_kind("stress_blend")
assert "service.methods.stress_blend.model" not in sys.modules
load = kind.load.function          # resolved: the model module is imported now
print(json.dumps({"modules": sorted(sys.modules),
                  "same": load == resolve("service.methods.stress_blend.model:StressBlendModel.load")}))
""")
    assert seen["same"] and "service.methods.stress_blend.model" in seen["modules"]
    assert "service.methods.pdm.model" not in seen["modules"]
