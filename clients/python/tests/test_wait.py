"""Waiting for jobs: event stream, the fallback to polling, cancellation, failures,
timeouts and progress display."""

from __future__ import annotations

import json
import sys

import httpx
import pytest

from facesynth_client import (Client, Job, JobCancelled, JobFailed, WaitTimeout)
from facesynth_client._core import SSEParser
from facesynth_client._progress import TextBar

from conftest import SHEET_MARKERS, upload_sheet_actor

SLOW_PDM = {"medium_resolution": 256, "fine_resolution": 512}  # ~12 s on the sheet


class FailingEvents(httpx.BaseTransport):
    """The real transport, except that ``/events`` requests fail (``mode``: a connection
    error or a 500) — counting what went where."""

    def __init__(self, mode: str):
        self.inner = httpx.HTTPTransport()
        self.mode = mode
        self.events = 0
        self.polls = 0

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            self.events += 1
            if self.mode == "connect":
                raise httpx.ConnectError("events unavailable", request=request)
            return httpx.Response(500, text="proxy error")
        if request.url.path.startswith("/v1/jobs/"):
            self.polls += 1
        return self.inner.handle_request(request)

    def close(self) -> None:
        self.inner.close()


def job_json(status: str, progress: float = 0.0, **extra) -> dict:
    return {"id": "job_1", "kind": "train", "status": status, "progress": progress,
            "stage": extra.pop("stage", ""), "actor_id": "act_1",
            "created_at": "2025-01-15T09:30:00Z", **extra}


# ---------------------------------------------------------------------------- real server
def test_cancel_a_queued_job_and_wait_raises_job_cancelled(idle_server):
    with Client(idle_server.url, poll_interval=0.05) as fs:
        actor = upload_sheet_actor(fs, "Idle")
        accepted = fs.models.train(actor.actor_id, "pdm", list(actor.clips.values()))
        assert fs.jobs.get(accepted).status == "queued"  # no worker on this server
        assert accepted.job_id in [j.id for j in fs.jobs.list(status="queued")]
        cancelled = fs.cancel(accepted)
        assert cancelled.status == "cancelled"
        with pytest.raises(JobCancelled) as caught:
            fs.wait(accepted, timeout=30)
        assert caught.value.job.id == accepted.job_id and caught.value.job.status == "cancelled"
        assert [j.status for j in fs.jobs.events(accepted)] == ["cancelled"]


def test_cancel_a_running_job_from_the_progress_callback(client, sheet_actor):
    accepted = client.models.train(sheet_actor.actor_id, "pdm",
                                   list(sheet_actor.clips.values()), SLOW_PDM)
    states: list[Job] = []

    def on_progress(job: Job) -> None:
        states.append(job)
        if job.status == "running" and len(states) < 50:
            assert client.cancel(job).status in ("running", "cancelled")

    with pytest.raises(JobCancelled):
        client.wait(accepted, timeout=60, progress=on_progress)
    assert "running" in [s.status for s in states]
    assert client.jobs.get(accepted).status == "cancelled"
    # a cancelled training reports the model cancelled (API 1 added the value; issue 22 item 16)
    assert client.models.get(accepted.model_id).status in ("cancelled", "training")


@pytest.mark.parametrize("mode", ["connect", "http500"])
def test_wait_falls_back_to_polling_when_the_event_stream_fails(server, sheet_actor, pdm_model,
                                                                mode):
    transport = FailingEvents(mode)
    with Client(server.url, transport=transport, poll_interval=0.05, max_retries=1,
                backoff=0.01) as fs:
        markers = sheet_actor.motions["rise"][:, list(SHEET_MARKERS)]
        accepted = fs.synthesis.submit_job(pdm_model, markers=markers)
        seen: list[Job] = []
        job = fs.wait(accepted, timeout=120, progress=seen.append)
    assert job.status == "succeeded" and job.artifact_ids
    assert transport.events >= 1 and transport.polls >= 2
    assert seen and seen[-1].status == "succeeded"


def test_events_iterate_a_running_job_to_its_end(client, sheet_actor, pdm_model):
    markers = sheet_actor.motions["fall"][:, list(SHEET_MARKERS)]
    accepted = client.synthesis.submit_job(pdm_model, markers=markers)
    states = list(client.jobs.events(accepted))
    assert states[-1].status == "succeeded" and all(not s.done for s in states[:-1])
    progress = [s.progress for s in states]
    assert progress == sorted(progress)


# ---------------------------------------------------------------------------- fake server
def fake(handler, **options) -> Client:
    return Client("http://fs.test", transport=httpx.MockTransport(handler), **options)


def test_wait_raises_job_failed_with_the_jobs_error():
    failed = job_json("failed", 0.3, error={"code": "invalid_input",
                                             "message": "training needs at least one clip"})

    def handler(request):
        body = "event: end\nid: 1\ndata: " + json.dumps(failed) + "\n\n"
        return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})

    with pytest.raises(JobFailed) as caught:
        fake(handler).wait("job_1")
    error = caught.value
    assert error.code == "invalid_input" and error.message == "training needs at least one clip"
    assert error.job.status == "failed" and "invalid_input" in str(error)


def test_wait_polls_after_a_broken_stream_and_times_out():
    polls = []

    def handler(request):
        if request.url.path.endswith("/events"):
            return httpx.Response(503, headers={"Retry-After": "0"})
        polls.append(request)
        return httpx.Response(200, json=job_json("running", 0.5))

    sleeps = []
    client = fake(handler, max_retries=0, poll_interval=0.01,
                  sleep=lambda s: (sleeps.append(s), __import__("time").sleep(s)))
    with pytest.raises(WaitTimeout) as caught:
        client.wait("job_1", timeout=0.2)
    assert isinstance(caught.value, TimeoutError)
    assert caught.value.job.status == "running" and len(polls) >= 2


def test_wait_polls_after_a_stream_that_ends_before_the_job():
    calls = {"events": 0, "polls": 0}

    def handler(request):
        if request.url.path.endswith("/events"):
            calls["events"] += 1
            body = ": keep-alive\n\nevent: progress\ndata: " + json.dumps(job_json("running", 0.4)) + "\n\n"
            return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})
        calls["polls"] += 1
        return httpx.Response(200, json=job_json("succeeded", 1.0,
                                                 result={"artifact_ids": ["art_1"]}))

    seen = []
    job = fake(handler, sleep=lambda s: None).wait("job_1", progress=seen.append)
    assert job.artifact_ids == ["art_1"]
    assert calls == {"events": 1, "polls": 1}
    assert [s.progress for s in seen] == [0.4, 1.0]


def test_progress_true_draws_a_text_bar_on_stderr(capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "tqdm", None)  # as if tqdm were not installed
    states = [job_json("running", 0.5, stage="fine band"), job_json("succeeded", 1.0)]

    def handler(request):
        body = "".join(f"event: {'end' if s['status'] == 'succeeded' else 'progress'}\n"
                       f"data: {json.dumps(s)}\n\n" for s in states)
        return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})

    fake(handler).wait("job_1", progress=True)
    err = capsys.readouterr().err
    assert "job_1" in err and " 50% fine band" in err and "100%" in err
    assert err.endswith("\n")


def test_progress_true_uses_tqdm_when_it_is_importable(capsys):
    pytest.importorskip("tqdm")
    states = [job_json("running", 0.25, stage="medium band"), job_json("succeeded", 1.0)]

    def handler(request):
        body = "".join(f"event: {'end' if s['status'] == 'succeeded' else 'progress'}\n"
                       f"data: {json.dumps(s)}\n\n" for s in states)
        return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})

    fake(handler).wait("job_1", progress=True)
    err = capsys.readouterr().err
    assert "job_1" in err and "100%" in err


def test_text_bar_clamps_and_redraws_in_place(capsys):
    bar = TextBar("j", width=10)
    bar.update(1.7, "x")
    bar.update(-1, "y")
    bar.close()
    err = capsys.readouterr().err
    assert "[##########] 100% x" in err and "[----------]   0% y" in err


def test_sse_parser_handles_split_chunks_crlf_comments_and_multiline_data():
    stream = (b": hello\r\n\r\nevent: progress\r\nid: 1\r\ndata: {\"a\":\r\ndata: 1}\r\n\r\n"
              b"event: end\ndata: {}\n\n")
    for size in (1, 2, 3, 7, len(stream)):
        parser, events = SSEParser(), []
        for k in range(0, len(stream), size):
            events += parser.feed(stream[k:k + size])
        assert [(e.event, e.data) for e in events] == [("progress", '{"a":\n1}'), ("end", "{}")]
        assert events[0].id == "1"


def test_an_exception_in_the_progress_callback_propagates_and_is_not_a_stream_failure():
    calls = {"events": 0, "polls": 0}

    def handler(request):
        key = "events" if request.url.path.endswith("/events") else "polls"
        calls[key] += 1
        body = "event: progress\ndata: " + json.dumps(job_json("running", 0.4)) + "\n\n"
        return httpx.Response(200, text=body, headers={"content-type": "text/event-stream"})

    def callback(job):
        raise ValueError("my bug")

    with pytest.raises(ValueError, match="my bug"):
        fake(handler).wait("job_1", progress=callback)
    assert calls == {"events": 1, "polls": 0}


def test_off_a_terminal_wait_progress_is_plain_lines(capsys):
    from types import SimpleNamespace

    from facesynth_client._progress import make_reporter

    report, close = make_reporter(True, "job_1")       # pytest's stderr is not a terminal
    for k in range(21):
        report(SimpleNamespace(progress=k / 20, stage="fit", status="running"))
    close()
    err = capsys.readouterr().err
    assert "\r" not in err
    assert err.splitlines() == [f"job_1 {p:3d}% fit" for p in range(0, 101, 10)]
