"""Prometheus metrics of one app (``GET /metrics``, text exposition format).

Each app has its own :class:`prometheus_client.CollectorRegistry`, so several apps (tests)
never share series. Collected:

- ``facesynth_http_request_duration_seconds`` histogram by method, route template and status;
- ``facesynth_jobs_queued`` gauge: jobs waiting in the queue, read from the database at
  each scrape;
- ``facesynth_job_duration_seconds`` histogram by job kind and final status: the jobs that
  finished since the previous scrape (the database is the truth, whichever worker ran them;
  with several API replicas each replica observes every job);
- ``facesynth_synthesis_frames_total`` counter and ``facesynth_synthesis_seconds_total``
  counter by model kind (their ratio is the synthesis rate in frames per second), and the
  ``facesynth_synthesis_fps`` gauge of the latest synchronous request;
- the model cache, read at each scrape (:meth:`Metrics.watch_cache`): gauges
  ``facesynth_model_cache_models`` (models loaded), ``facesynth_model_cache_bytes`` (their
  weighed size) and ``facesynth_model_cache_budget_bytes``, and counters
  ``facesynth_model_cache_hits_total`` and ``facesynth_model_cache_misses_total`` (loads).
"""

from __future__ import annotations

import threading
from datetime import datetime
from typing import Any, Iterable

from prometheus_client import (CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge,
                               Histogram, generate_latest)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import select
from sqlalchemy.orm import Session

from models_store import registry
from models_store.cache import ByteLRUCache
from models_store.schema import Job, utcnow

CONTENT_TYPE = CONTENT_TYPE_LATEST
#: buckets of request latency, seconds
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60)
#: buckets of job durations, seconds
JOB_BUCKETS = (1, 5, 15, 30, 60, 120, 300, 600, 1200, 3600, 7200, 21600)


class Metrics:
    """The metrics of one app (see the module docstring)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.request_duration = Histogram(
            "facesynth_http_request_duration_seconds", "HTTP request latency",
            ["method", "route", "status"], buckets=LATENCY_BUCKETS, registry=self.registry)
        self.jobs_queued = Gauge("facesynth_jobs_queued", "Jobs waiting in the queue",
                                 registry=self.registry)
        self.job_duration = Histogram(
            "facesynth_job_duration_seconds", "Duration of finished jobs (start to finish)",
            ["kind", "status"], buckets=JOB_BUCKETS, registry=self.registry)
        self.synthesis_frames = Counter(
            "facesynth_synthesis_frames", "Frames synthesized by synchronous requests",
            ["kind"], registry=self.registry)
        self.synthesis_seconds = Counter(
            "facesynth_synthesis_seconds", "Time spent synthesizing those frames",
            ["kind"], registry=self.registry)
        self.synthesis_fps = Gauge(
            "facesynth_synthesis_fps", "Frames per second of the latest synchronous synthesis",
            ["kind"], registry=self.registry)
        self.synthesis_queue_depth = Gauge(
            "facesynth_synthesis_queue_depth",
            "Synchronous syntheses waiting for a slot", registry=self.registry)
        self.synthesis_running = Gauge(
            "facesynth_synthesis_running",
            "Syntheses running (HTTP requests and gRPC stream frames: one pool of slots)",
            registry=self.registry)
        self._finished_since: datetime = utcnow()
        self._lock = threading.Lock()
        self._cache = _CacheCollector()
        self.registry.register(self._cache)

    def watch_cache(self, cache: ByteLRUCache[Any]) -> None:
        """Report ``cache`` (the process's model cache) at each scrape."""
        self._cache.cache = cache

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        """Record one answered HTTP request."""
        self.request_duration.labels(method, route, str(status)).observe(seconds)

    def observe_synthesis(self, kind: str, frames: int, seconds: float) -> None:
        """Record one synchronous synthesis of ``frames`` frames."""
        self.synthesis_frames.labels(kind).inc(frames)
        self.synthesis_seconds.labels(kind).inc(seconds)
        if seconds > 0:
            self.synthesis_fps.labels(kind).set(frames / seconds)

    def refresh_jobs(self, session: Session) -> None:
        """Read the queue depth and the jobs finished since the last call from the database."""
        self.jobs_queued.set(len(registry.list_jobs(session, status="queued")))
        with self._lock:
            since = self._finished_since
            rows = session.execute(
                select(Job.kind, Job.status, Job.started_at, Job.finished_at)
                .where(Job.finished_at > since).order_by(Job.finished_at)).all()
            for kind, status, started, finished in rows:
                if started is not None:
                    self.job_duration.labels(kind, status).observe(
                        max(0.0, (finished - started).total_seconds()))
                self._finished_since = max(self._finished_since, finished)

    def render(self) -> bytes:
        """The text exposition of every metric."""
        return generate_latest(self.registry)


class _CacheCollector(Collector):
    """The model cache's state, read when scraped (nothing before :meth:`watch_cache`)."""

    def __init__(self) -> None:
        self.cache: ByteLRUCache[Any] | None = None

    def describe(self) -> Iterable[Metric]:
        return []

    def collect(self) -> Iterable[Metric]:
        cache = self.cache
        if cache is None:
            return
        yield GaugeMetricFamily("facesynth_model_cache_models", "Models loaded in the cache",
                                value=len(cache))
        yield GaugeMetricFamily("facesynth_model_cache_bytes",
                                "Weighed size of the models in the cache", value=cache.total_bytes)
        yield GaugeMetricFamily("facesynth_model_cache_budget_bytes",
                                "Byte budget of the model cache", value=cache.budget_bytes)
        yield CounterMetricFamily("facesynth_model_cache_hits",
                                  "Model lookups answered from the cache", value=cache.hits)
        yield CounterMetricFamily("facesynth_model_cache_misses",
                                  "Model lookups that loaded the model", value=cache.misses)
