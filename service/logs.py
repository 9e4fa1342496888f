"""Structured logs: one JSON object per line, with the id of the request or job at hand.

Every process (``facesynth serve``, ``facesynth worker``) logs through :func:`configure_logging`.
A record carries ``request_id`` while an HTTP request is served (set by the API's middleware)
and ``job_id`` while a worker runs a job (set by :mod:`service.jobs.runner`), so one grep
follows a request or a job across processes.
"""

from __future__ import annotations

import contextvars
import json
import logging
import sys
from datetime import datetime, timezone
from typing import Any

#: the id of the request being served (empty outside a request)
request_id_var: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="")
#: the id of the job being run (empty outside a job)
job_id_var: contextvars.ContextVar[str] = contextvars.ContextVar("job_id", default="")
_STANDARD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime", "color_message"}
#: loggers too chatty at INFO (alembic announces every plugin on each migration check)
_QUIET = ("alembic",)


class JsonFormatter(logging.Formatter):
    """Formats a record as one JSON line: ``ts, level, logger, message, request_id``, the
    record's ``extra`` fields, and ``exc`` with the traceback if any."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, Any] = {
            "ts": datetime.fromtimestamp(record.created, timezone.utc).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        request_id = getattr(record, "request_id", None) or request_id_var.get()
        if request_id:
            entry["request_id"] = request_id
        job_id = getattr(record, "job_id", None) or job_id_var.get()
        if job_id:
            entry["job_id"] = job_id
        for key, value in vars(record).items():
            if key not in _STANDARD and key not in entry:
                entry[key] = value
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def configure_logging(level: int | str = logging.INFO) -> None:
    """Send every log record (ours, uvicorn's, grpc's) to stderr as JSON lines."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access"):
        logger = logging.getLogger(name)
        logger.handlers[:] = []
        logger.propagate = True
    for name in _QUIET:
        logging.getLogger(name).setLevel(logging.WARNING)
