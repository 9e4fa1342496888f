"""Settings of the service, read from ``FACESYNTH_*`` environment variables.

One :class:`Settings` class, every field with a default, so ``Settings()`` works on a fresh
machine and a test builds ``Settings(data_dir=tmp_path)`` with nothing in the environment.
Nothing is read at import time: the process-wide instance comes from the cached
:func:`get_settings`, which the API injects as a dependency.

Examples
--------
>>> Settings(data_dir="/srv/facesynth").database_url_resolved
'sqlite:////srv/facesynth/facesynth.db'

In the environment, ``FACESYNTH_TOKENS=alpha,beta`` gives ``tokens == ["alpha", "beta"]``
(a JSON list works too).
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

MiB = 1 << 20
GiB = 1 << 30


class Settings(BaseSettings):
    """Configuration of the API server and the workers.

    Every field is the environment variable ``FACESYNTH_<FIELD>`` (case-insensitive).
    """

    model_config = SettingsConfigDict(env_prefix="FACESYNTH_", extra="ignore",
                                      validate_default=True,
                                      hide_input_in_errors=True)  # never echo a token

    # -- storage -----------------------------------------------------------------------------
    data_dir: Path = Field(
        default=Path("./facesynth-data"),
        description="Directory holding the default SQLite database, the blob store and the "
                    "embedded queue.")
    database_url: str | None = Field(
        default=None,
        description="SQLAlchemy URL of the metadata database, e.g. "
                    "'postgresql://user@db/facesynth'. None: the SQLite file "
                    "<data_dir>/facesynth.db.")
    queue_url: str | None = Field(
        default=None,
        description="URL of the task queue's storage, e.g. 'redis://queue:6379/0'. None: the "
                    "embedded queue in the data directory (one machine); 'memory://': run "
                    "every job at once in the submitting thread (tests).")
    queue_name: str = Field(
        default="facesynth", min_length=1, max_length=100, pattern=r"^[A-Za-z0-9_]+$",
        description="Name of the task queue; its Redis keys are 'huey.*.<queue_name>'. "
                    "Deployments (or test runs) sharing one Redis use different names.")

    # -- network -----------------------------------------------------------------------------
    host: str = Field(default="127.0.0.1", description="Address the HTTP API listens on.")
    port: int = Field(default=8000, ge=1, le=65535, description="Port of the HTTP API.")
    grpc_port: int = Field(default=50051, ge=1, le=65535,
                           description="Port of the gRPC streaming server.")
    workers: int = Field(default=1, ge=0,
                         description="Number of job worker threads to run; 0 makes "
                                     "`facesynth serve` an API-only process (jobs then run "
                                     "on separate `facesynth worker` processes, which need "
                                     "at least 1).")
    tokens: Annotated[list[str], NoDecode] = Field(
        default_factory=list, repr=False,
        description="Accepted bearer tokens; in the environment a comma-separated list (or a "
                    "JSON list). Each entry is TOKEN (tenant 'default'), TENANT:TOKEN or "
                    "TENANT:TOKEN:admin (sees every tenant); TOKEN may be "
                    "'sha256:<hex digest of the token>' so the token itself is not stored "
                    "(models_store.tenancy). Empty: no authentication, and the API only listens "
                    "on loopback.")
    public_health: bool = Field(
        default=True,
        description="/healthz and /readyz answer without a token (for probes); false: they "
                    "need one like /v1.")
    public_metrics: bool = Field(
        default=True,
        description="/metrics answers without a token (for scrapers); false: it needs one.")
    public_docs: bool = Field(
        default=True,
        description="The OpenAPI schema and its pages (/openapi.json, /docs, /redoc) answer "
                    "without a token; false: they need one.")

    # -- limits ------------------------------------------------------------------------------
    max_body_bytes: int = Field(default=256 * MiB, ge=1,
                                description="Largest accepted request body, in bytes (413 above).")
    spool_body_bytes: int = Field(
        default=8 * MiB, ge=0,
        description="Request bodies larger than this are spooled to a hidden file in the "
                    "blob store while they are hashed, not gathered in memory chunk by chunk.")
    max_concurrent_uploads: int = Field(
        default=4, ge=1,
        description="Most requests with a body over spool_body_bytes received at once; more "
                    "wait up to upload_queue_seconds, then get 503 with Retry-After.")
    upload_queue_seconds: float = Field(
        default=30.0, ge=0,
        description="How long a large upload waits for its turn (max_concurrent_uploads).")
    max_frames_per_request: int = Field(
        default=64, ge=1,
        description="Most frames a synchronous synthesis request may carry (413 above; larger "
                    "work goes to a synthesis job).")
    max_concurrent_syntheses: int | None = Field(
        default=None, ge=1,
        description="Synchronous syntheses (and enhancements) run at once, HTTP requests and "
                    "gRPC stream frames together (one pool); None: one per CPU core of the "
                    "machine.")
    blas_threads: int | None = Field(
        default=None, ge=1,
        description="BLAS/OpenMP threads of each synthesis (OPENBLAS_NUM_THREADS, "
                    "OMP_NUM_THREADS, MKL_NUM_THREADS of `serve`, set before NumPy loads); "
                    "None: the CPU cores divided by max_concurrent_syntheses (at least 1), "
                    "so slots x threads fill the cores without oversubscribing them, unless "
                    "those variables are already set.")
    synthesis_kernel_threads: Literal["slot", "share"] = Field(
        default="slot",
        description="Threads of a synthesis's compiled per-frame kernels: slot, the per-slot "
                    "count (NUMBA_NUM_THREADS, sized with the BLAS threads); share, the CPU "
                    "cores divided among the syntheses running when it starts, so a lone "
                    "request uses every core (level-1 maps frame ~43 -> ~31 ms on 2 cores; "
                    "best with one BLAS thread per slot).")
    synthesis_queue_seconds: float = Field(
        default=30.0, ge=0,
        description="How long a synchronous synthesis waits for a free slot before it is "
                    "answered 503 with Retry-After.")
    synthesis_queue_depth: int = Field(
        default=64, ge=0,
        description="Most synchronous syntheses waiting for a slot at once; more are "
                    "answered 503 at once. /metrics: facesynth_synthesis_queue_depth.")
    max_map_resolution: int = Field(default=4096, ge=1,
                                    description="Largest UV-space map side, in texels.")
    max_vertices: int = Field(default=2_000_000, ge=1,
                              description="Most vertices an uploaded mesh may have.")
    model_cache_bytes: int = Field(
        default=2 * GiB, ge=0,
        description="Memory budget of the in-process cache of loaded models, in bytes.")
    preload: Annotated[list[str], NoDecode] = Field(
        default_factory=list,
        description="Models `facesynth serve` loads into the cache at start-up, in the "
                    "background while it already serves: model ids, or 'all' for every "
                    "ready model; in the environment a comma-separated list. /readyz answers "
                    "503 (check 'models') until they are loaded, so a probe sends no traffic "
                    "before the first frame can be answered without the load.")

    header_timeout_seconds: float = Field(
        default=10.0, gt=0,
        description="A request's headers must arrive within this many seconds of its first "
                    "byte (408 and the connection closed otherwise); also the longest stall "
                    "allowed inside a body.")
    min_body_rate_bytes: float = Field(
        default=1024.0, ge=0,
        description="After body_rate_grace_seconds, a request body must arrive at an average "
                    "of at least this many bytes per second, or the connection is closed.")
    body_rate_grace_seconds: float = Field(
        default=10.0, gt=0,
        description="How long a request body may arrive at any rate before "
                    "min_body_rate_bytes applies.")
    max_connections_per_client: int = Field(
        default=32, ge=1,
        description="Most simultaneous HTTP connections from one client address; one more is "
                    "answered 503 and closed.")
    http: Literal["auto", "h11", "httptools"] = Field(
        default="auto",
        description="uvicorn's HTTP parser: h11 (pure Python) or httptools (C, from "
                    "uvicorn[standard]); auto: httptools when installed. Both hold the "
                    "header/body timeouts and the per-client bound above.")
    lean_synthesis: bool = Field(
        default=True,
        description="POST /v1/models/{id}/synthesize with a plain query string is served on "
                    "a lean ASGI path (service/api/lean.py: the same answers, without "
                    "FastAPI's routing and dependency solving); false: through FastAPI like "
                    "every other route.")
    opentelemetry: bool = Field(
        default=False,
        description="FastAPI's own OpenTelemetry spans, metrics and logs, sent to the globally "
                    "configured providers (e.g. under opentelemetry-instrument); false: the "
                    "service's /metrics and JSON logs only, and FastAPI no longer looks the "
                    "providers up on every request (~0.03-0.08 ms of a request's server CPU).")
    loop: Literal["auto", "asyncio", "uvloop"] = Field(
        default="auto",
        description="The HTTP server's event loop: asyncio, or uvloop (from "
                    "uvicorn[standard]); auto: uvloop when installed.")

    # -- jobs --------------------------------------------------------------------------------
    job_max_retries: int = Field(
        default=2, ge=0,
        description="How often a job whose worker died is requeued before it is failed.")
    job_lease_seconds: float = Field(
        default=60.0, gt=0,
        description="A running job's lease; a worker renews it by heartbeats, and a job whose "
                    "lease expired is requeued or failed.")

    job_resubmit_seconds: float = Field(
        default=30.0, gt=0, le=3600,
        description="A queued job with no message waiting in the queue this long after it "
                    "was created (the message was lost) is resubmitted; every API and worker "
                    "process checks each maintenance round.")
    maintenance_interval_seconds: float = Field(
        default=5.0, gt=0, le=300,
        description="Pause between maintenance rounds (reaping expired leases, resubmitting "
                    "lost queued jobs), run by every worker and API process; shorter for "
                    "short leases (a quarter lease).")

    # -- storage hygiene and readiness -----------------------------------------------------
    stale_temporary_seconds: float = Field(
        default=900.0, gt=0,
        description="A temporary in the blob store (a half-written blob, a job's scratch "
                    "directory) left by a crash is removed once nothing in it changed for "
                    "this long; a scratch directory in use is never removed.")
    temporary_sweep_seconds: float = Field(
        default=300.0, gt=0,
        description="Pause between sweeps of stale temporaries (also swept at start-up).")
    min_free_bytes: int = Field(
        default=256 * MiB, ge=0,
        description="/readyz answers 503 when the blob store has less free space than this, "
                    "in bytes (or cannot be written).")

    @field_validator("tokens", "preload", mode="before")
    @classmethod
    def _split_list(cls, value: Any) -> Any:
        """Accept ``"a,b"`` and ``'["a","b"]'`` as well as a list; drop blanks."""
        if isinstance(value, str):
            text = value.strip()
            value = json.loads(text) if text.startswith("[") else text.split(",")
        if isinstance(value, (list, tuple)):
            return [str(t).strip() for t in value if str(t).strip()]
        return value

    @field_validator("tokens")
    @classmethod
    def _check_tokens(cls, value: list[str]) -> list[str]:
        """Every entry parses (models_store.tenancy.parse_entry); the error never shows a token."""
        from models_store.tenancy import parse_entry

        for number, entry in enumerate(value, 1):
            try:
                parse_entry(entry)
            except ValueError as error:
                raise ValueError(f"token entry {number}: {error}") from None
        return value

    @property
    def database_url_resolved(self) -> str:
        """The database URL to connect to: ``database_url``, or the SQLite file in the data
        directory (absolute, so every process started anywhere finds the same file)."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'facesynth.db').absolute()}"

    @property
    def blob_dir(self) -> Path:
        """Root of the blob store, ``<data_dir>/blobs``."""
        return self.data_dir / "blobs"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment on first call and cached.

    Tests that change the environment call ``get_settings.cache_clear()``.
    """
    return Settings()
