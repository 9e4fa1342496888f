"""service/logs.py: JSON lines carrying the request and job at hand."""

import json
import logging

from service.logs import JsonFormatter, job_id_var, request_id_var


def _line(**extra) -> dict:
    record = logging.makeLogRecord({"name": "facesynth.test", "levelno": logging.INFO,
                                    "levelname": "INFO", "msg": "step %d", "args": (3,), **extra})
    return json.loads(JsonFormatter().format(record))


def test_json_line_carries_the_job_id_set_for_the_running_job():
    token = job_id_var.set("job_0123456789abcdefghjkmnpqrs")
    try:
        entry = _line()
    finally:
        job_id_var.reset(token)
    assert entry["job_id"] == "job_0123456789abcdefghjkmnpqrs"
    assert entry["message"] == "step 3" and entry["level"] == "info"
    assert "request_id" not in entry
    assert "job_id" not in _line()


def test_json_line_keeps_extra_fields_and_prefers_the_record_request_id():
    token = request_id_var.set("from-context")
    try:
        entry = _line(request_id="from-record", frames=12)
    finally:
        request_id_var.reset(token)
    assert entry["request_id"] == "from-record" and entry["frames"] == 12
