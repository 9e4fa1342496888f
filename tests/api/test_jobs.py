"""Jobs (state, filters, cancellation, server-sent events) and artifact downloads."""

from __future__ import annotations

import hashlib
import json
import threading
import time

import pytest

from models_store import registry
from service.app import limits
from tests.api.conftest import assert_problem


@pytest.fixture
def services(client):
    return client.app.state.services


def _job(services, actor_id, kind="synthesize"):
    with services.session() as session:
        return registry.create_job(session, kind, actor_id, payload={"x": 1}).id


def _claim(services, job_id):
    with services.session() as session:
        registry.claim_job(session, "w1", lease_seconds=60, max_retries=1, job_id=job_id)


def test_get_and_list_jobs_with_filters(client, services, actor_id):
    a = _job(services, actor_id, "synthesize")
    b = _job(services, actor_id, "register")
    _claim(services, b)
    job = client.get(f"/v1/jobs/{a}").json()
    assert (job["id"], job["status"], job["progress"], job["kind"]) == (a, "queued", 0.0, "synthesize")
    assert job["error"] is None and job["result"] is None and job["started_at"] is None
    ids = lambda **q: [j["id"] for j in client.get("/v1/jobs", params=q).json()["items"]]
    assert ids() == [a, b]
    assert ids(status="running") == [b]
    assert ids(kind="synthesize", actor_id=actor_id) == [a]
    assert ids(actor_id="act_00000000000000000000000000") == []
    assert_problem(client.get("/v1/jobs", params={"status": "done"}), 422, "status")
    assert_problem(client.get("/v1/jobs/job_00000000000000000000000000"), 404)


def test_cancel_queued_and_running_jobs(client, services, actor_id):
    queued, running = _job(services, actor_id), _job(services, actor_id)
    _claim(services, running)
    response = client.delete(f"/v1/jobs/{queued}")
    assert response.status_code == 200 and response.json()["status"] == "cancelled"
    response = client.delete(f"/v1/jobs/{running}")
    assert response.status_code == 202
    assert response.json()["status"] == "running"
    with services.session() as session:
        assert registry.get_job(session, running).cancel_requested
    assert client.delete(f"/v1/jobs/{queued}").status_code == 200      # idempotent
    assert_problem(client.delete("/v1/jobs/job_00000000000000000000000000"), 404)


def _events(text: str) -> list[tuple[str, str]]:
    out = []
    for block in text.strip().split("\n\n"):
        fields = dict(line.split(": ", 1) for line in block.splitlines() if not line.startswith(":"))
        out.append((fields["event"], fields["data"]))
    return out


def test_events_of_a_finished_job_is_one_end_event(client, services, actor_id):
    job_id = _job(services, actor_id)
    client.delete(f"/v1/jobs/{job_id}")
    response = client.get(f"/v1/jobs/{job_id}/events")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/event-stream")
    events = _events(response.text)
    assert [e for e, _ in events] == ["end"] and '"cancelled"' in events[0][1]


def test_events_follow_progress_until_the_job_ends(client, services, actor_id, monkeypatch):
    monkeypatch.setattr(limits, "EVENTS_POLL_SECONDS", 0.02)
    job_id = _job(services, actor_id)
    _claim(services, job_id)

    def work():
        for fraction in (0.25, 0.5, 0.75):
            time.sleep(0.15)
            with services.session() as session:
                registry.update_job_progress(session, job_id, fraction, "fitting")
        time.sleep(0.15)
        with services.session() as session:
            registry.finish_job(session, job_id, "succeeded", result={"artifact_ids": []})

    thread = threading.Thread(target=work)
    thread.start()
    response = client.get(f"/v1/jobs/{job_id}/events")
    thread.join()
    events = _events(response.text)
    assert events[-1][0] == "end" and '"succeeded"' in events[-1][1]
    assert [e for e, _ in events[:-1]] == ["progress"] * (len(events) - 1)
    # the stream polls, so under load it may coalesce states, never reorder or invent them
    seen = [json.loads(data)["progress"] for _, data in events[:-1]]
    assert seen and seen == sorted(seen) and set(seen) <= {0.0, 0.25, 0.5, 0.75, 1.0}


def test_events_of_unknown_job_is_404(client):
    assert_problem(client.get("/v1/jobs/job_00000000000000000000000000/events"), 404)


@pytest.fixture
def artifact(client, services, actor_id):
    job_id = _job(services, actor_id)
    data = bytes(range(256)) * 40
    with services.session() as session:
        row = registry.add_artifact(session, services.blobs, job_id, data,
                                    media_type="application/x-npz", filename="result.npz")
    return row.id, job_id, data


def test_artifact_download_with_etag_and_length(client, artifact):
    artifact_id, job_id, data = artifact
    response = client.get(f"/v1/artifacts/{artifact_id}")
    assert response.status_code == 200 and response.content == data
    assert response.headers["content-length"] == str(len(data))
    assert response.headers["etag"] == f'"{hashlib.sha256(data).hexdigest()}"'
    assert response.headers["accept-ranges"] == "bytes"
    assert response.headers["content-type"] == "application/x-npz"
    listed = client.get(f"/v1/jobs/{job_id}/artifacts").json()["items"]
    assert [a["id"] for a in listed] == [artifact_id] and listed[0]["size_bytes"] == len(data)


def test_artifact_range_conditional_and_unknown(client, artifact):
    artifact_id, _, data = artifact
    url = f"/v1/artifacts/{artifact_id}"
    part = client.get(url, headers={"Range": "bytes=100-199"})
    assert part.status_code == 206 and part.content == data[100:200]
    assert part.headers["content-range"] == f"bytes 100-199/{len(data)}"
    tail = client.get(url, headers={"Range": "bytes=-10"})
    assert tail.status_code == 206 and tail.content == data[-10:]
    assert client.get(url, headers={"Range": f"bytes={len(data)}-"}).status_code == 416
    etag = client.get(url).headers["etag"]
    assert client.get(url, headers={"If-None-Match": etag}).status_code == 304
    assert client.get(url, headers={"If-None-Match": '"other"'}).status_code == 200
    assert client.get(url, headers={"Range": "bytes=0-9", "If-Range": '"stale"'}).status_code == 200
    assert_problem(client.get("/v1/artifacts/art_00000000000000000000000000"), 404)
    assert_problem(client.get("/v1/artifacts/..%2f..%2fsecret"), 404)
