"""``facesynth serve``: the HTTP API, gRPC and embedded workers in one process."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time

import grpc
import httpx
import numpy as np
import pytest

from service.cli import main
from service.grpc import codec
from service.grpc.facesynth.v1 import synthesis_pb2_grpc as pb_grpc


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_refuses_a_public_host_without_tokens(capsys, monkeypatch):
    monkeypatch.delenv("FACESYNTH_TOKENS", raising=False)
    assert main(["serve", "--host", "0.0.0.0"]) == 2
    assert "refusing to listen on 0.0.0.0 without tokens" in capsys.readouterr().err


@pytest.mark.parametrize("busy", ["http", "grpc"])
def test_serve_with_a_port_in_use_is_one_line_naming_the_option_and_exit_2(
        busy, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("service.logs.configure_logging", lambda *a, **k: None)
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen(1)
        taken = holder.getsockname()[1]
        port, grpc_port = (taken, free_port()) if busy == "http" else (free_port(), taken)
        code = main(["serve", "--port", str(port), "--grpc-port", str(grpc_port),
                     "--data-dir", str(tmp_path), "--workers", "0"])
    err = capsys.readouterr().err
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    option = "--port" if busy == "http" else "--grpc-port"
    assert f"127.0.0.1:{taken}" in err and option in err
    assert ("--grpc-port" in err) == (busy == "grpc")


def test_serve_preload_of_an_unknown_model_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("service.logs.configure_logging", lambda *a, **k: None)
    code = main(["serve", "--port", str(free_port()), "--grpc-port", str(free_port()),
                 "--data-dir", str(tmp_path), "--workers", "0",
                 "--preload", "mdl_00000000000000000000000000"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("facesynth serve: --preload: ") and len(err.splitlines()) == 1


def test_serve_runs_http_grpc_and_workers(tmp_path):
    port, grpc_port = free_port(), free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    process = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--grpc-port",
         str(grpc_port), "--data-dir", str(tmp_path), "--workers", "1"],
        stderr=subprocess.PIPE, text=True, env=env)
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"{base}/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert process.poll() is None, process.stderr.read()
            assert time.monotonic() < deadline, "the server did not start"
            time.sleep(0.2)
        ready = httpx.get(f"{base}/readyz", headers={"X-Request-ID": "serve-test"})
        assert ready.status_code == 200, ready.text
        assert ready.headers["x-request-id"] == "serve-test"
        actor = httpx.post(f"{base}/v1/actors", json={"name": "Ada"}).json()
        assert actor["name"] == "Ada"
        with grpc.insecure_channel(f"127.0.0.1:{grpc_port}") as channel:
            stub = pb_grpc.SynthesisStub(channel)
            first = codec.encode_markers(np.zeros((3, 3)), 0,
                                         model_id="mdl_00000000000000000000000000")
            with pytest.raises(grpc.RpcError) as error:
                list(stub.StreamSynthesize(iter([first]), timeout=10))
            assert error.value.code() == grpc.StatusCode.NOT_FOUND
    finally:
        process.send_signal(signal.SIGINT)
        try:
            _, stderr = process.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            process.kill()
            _, stderr = process.communicate()
    assert process.returncode == 0, stderr
    records = [json.loads(line) for line in stderr.splitlines() if line.startswith("{")]
    started = [r for r in records if r["logger"] == "facesynth.serve"]
    assert len(started) == 1, stderr
    assert (started[0]["http"], started[0]["grpc"]) == (f"127.0.0.1:{port}", f"127.0.0.1:{grpc_port}")
    assert f"http://127.0.0.1:{port}" in started[0]["message"]
    assert f"gRPC on 127.0.0.1:{grpc_port}" in started[0]["message"]
    access = [r for r in records if r["logger"] == "facesynth.access"]
    assert any(entry.get("request_id") == "serve-test" and entry["route"] == "/readyz"
               for entry in access)


@pytest.mark.parametrize("url, workers", [("amqp://queue", "0"), ("memory://", "1")])
def test_serve_with_a_queue_url_of_the_wrong_form_is_one_line_and_exit_2(
        url, workers, tmp_path, capsys, monkeypatch):
    """The queue URL's form is checked at start, before anything loads (no Huey imported:
    ``service.jobs.queue_storage``); a reachable-but-down queue fails /readyz instead."""
    monkeypatch.setenv("FACESYNTH_QUEUE_URL", url)
    code = main(["serve", "--port", str(free_port()), "--grpc-port", str(free_port()),
                 "--data-dir", str(tmp_path), "--workers", workers])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("facesynth serve: FACESYNTH_QUEUE_URL: ")
    assert len(err.splitlines()) == 1


#: ``facesynth serve --preload`` in a fresh interpreter whose model load waits for a gate:
#: what /readyz says and what is imported while it loads, then after it
_PRELOAD_SCRIPT = r"""
import json, os, signal, sys, threading, time
import httpx
from service.app.services import Services
from service.cli import main

gate = threading.Event()
Services.preload_ids = lambda self, models: list(models)
Services.loaded_model = lambda self, model_id: gate.wait(60)
Services.warm_up = lambda self, loaded: True
port, grpc_port, data_dir = sys.argv[1:4]

def state():
    response = httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=5)
    return {"status": response.status_code, "checks": response.json()["checks"],
            "imported": sorted(m for m in ("huey", "redis", "psycopg", "service.jobs.worker")
                               if m in sys.modules),
            "worker": any(t.name == "facesynth-worker" for t in threading.enumerate())}

def watch():
    seen = {}
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            seen["loading"] = state()
            break
        except httpx.TransportError:
            time.sleep(0.05)
    gate.set()
    while time.monotonic() < deadline and not state()["worker"]:
        time.sleep(0.05)
    seen["loaded"] = state()
    print(json.dumps(seen), flush=True)
    os.kill(os.getpid(), signal.SIGINT)

threading.Thread(target=watch, daemon=True).start()
sys.exit(main(["serve", "--port", port, "--grpc-port", grpc_port, "--data-dir", data_dir,
               "--workers", "1", "--preload", "mdl_00000000000000000000000000"]))
"""


def test_serve_with_a_preload_starts_its_workers_and_imports_huey_once_the_models_are_loaded(tmp_path):
    """Issue 23's cold start: while a preload loads, /readyz answers 503 (``models``) with
    the queue probed without Huey, and neither Huey (nor the redis and psycopg it imports)
    nor the worker module is imported; once the models are loaded the embedded worker
    starts and /readyz answers 200."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("FACESYNTH_")}
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env["PYTHONPATH"] = root
    result = subprocess.run([sys.executable, "-c", _PRELOAD_SCRIPT, str(free_port()),
                             str(free_port()), str(tmp_path)], cwd=root, env=env,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    loading, loaded = seen["loading"], seen["loaded"]
    assert loading["status"] == 503 and loading["checks"]["queue"] == "ok"
    assert loading["checks"]["models"] == "loading: 0 of 1 preloaded"
    assert loading["imported"] == [] and not loading["worker"]
    assert loaded["status"] == 200 and set(loaded["checks"].values()) == {"ok"}
    assert loaded["worker"] and {"huey", "service.jobs.worker"} <= set(loaded["imported"])
