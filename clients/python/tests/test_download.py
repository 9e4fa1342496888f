"""Artifact downloads: atomic writes, checksum checks, and resuming with ``Range``."""

from __future__ import annotations

import hashlib

import httpx
import pytest

from facesynth_client import Client, IntegrityError, NotFound

CONTENT = bytes(range(256)) * 400  # 102400 bytes
SHA = hashlib.sha256(CONTENT).hexdigest()
ETAG = f'"{SHA}"'


class BreakingStream(httpx.SyncByteStream):
    """A body that breaks with a read error after ``limit`` bytes."""

    def __init__(self, data: bytes, limit: int):
        self.data, self.limit = data, limit

    def __iter__(self):
        yield self.data[:self.limit]
        raise httpx.ReadError("connection reset")


class ArtifactServer:
    """A fake ``GET /v1/artifacts/{id}`` with ETag, Range and If-Range; ``break_after``
    bytes into the first full answer it breaks the connection."""

    def __init__(self, content: bytes = CONTENT, etag: str = ETAG, break_after: int | None = None):
        self.content, self.etag, self.break_after = content, etag, break_after
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if not request.url.path.startswith("/v1/artifacts/art_1"):
            return httpx.Response(404, json={"status": 404, "title": "Not Found",
                                             "detail": "no such artifact"})
        headers = {"etag": self.etag, "accept-ranges": "bytes"}
        ranged = request.headers.get("range")
        if ranged and request.headers.get("if-range", self.etag) == self.etag:
            start = int(ranged.split("=")[1].split("-")[0])
            body = self.content[start:]
            headers["content-range"] = f"bytes {start}-{len(self.content) - 1}/{len(self.content)}"
            return httpx.Response(206, headers={**headers, "content-length": str(len(body))},
                                  content=body)
        headers["content-length"] = str(len(self.content))
        if self.break_after is not None:
            limit, self.break_after = self.break_after, None
            return httpx.Response(200, headers=headers, stream=BreakingStream(self.content, limit))
        return httpx.Response(200, headers=headers, content=self.content)


def client_for(server, **options) -> Client:
    return Client("http://fs.test", transport=httpx.MockTransport(server), sleep=lambda s: None,
                  **options)


def test_download_writes_atomically_and_checks_the_etag(tmp_path):
    server = ArtifactServer()
    path = client_for(server).download_artifact("art_1", tmp_path / "a.npz")
    assert path == tmp_path / "a.npz" and path.read_bytes() == CONTENT
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]


def test_a_connection_lost_mid_download_is_resumed_with_range(tmp_path):
    server = ArtifactServer(break_after=30000)
    path = client_for(server).download_artifact("art_1", tmp_path / "a.npz")
    assert path.read_bytes() == CONTENT
    assert len(server.requests) == 2
    assert server.requests[1].headers["range"] == "bytes=30000-"
    assert server.requests[1].headers["if-range"] == ETAG


def test_a_partial_file_from_an_earlier_attempt_is_resumed(tmp_path):
    (tmp_path / "a.npz.part").write_bytes(CONTENT[:5000])
    (tmp_path / "a.npz.part.etag").write_text(ETAG)
    server = ArtifactServer()
    client_for(server).download_artifact("art_1", tmp_path / "a.npz")
    assert (tmp_path / "a.npz").read_bytes() == CONTENT
    assert server.requests[0].headers["range"] == "bytes=5000-"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz"]


def test_a_partial_file_of_a_changed_artifact_is_downloaded_again(tmp_path):
    (tmp_path / "a.npz.part").write_bytes(b"x" * 5000)
    (tmp_path / "a.npz.part.etag").write_text('"old"')
    server = ArtifactServer()
    client_for(server).download_artifact("art_1", tmp_path / "a.npz")
    assert (tmp_path / "a.npz").read_bytes() == CONTENT


def test_without_resume_a_broken_download_fails_and_leaves_no_file(tmp_path):
    from facesynth_client import TransportError
    server = ArtifactServer(break_after=1000)
    with pytest.raises(TransportError):
        client_for(server).download_artifact("art_1", tmp_path / "a.npz", resume=False)
    assert not (tmp_path / "a.npz").exists()


def test_a_checksum_mismatch_raises_and_keeps_nothing(tmp_path):
    server = ArtifactServer(etag='"' + "0" * 64 + '"')
    with pytest.raises(IntegrityError):
        client_for(server).download_artifact("art_1", tmp_path / "a.npz")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(IntegrityError):
        client_for(ArtifactServer()).download_artifact("art_1", tmp_path / "b.npz",
                                                       sha256="f" * 64)
    client_for(ArtifactServer(etag='"not-a-sha"')).download_artifact(
        "art_1", tmp_path / "c.npz", sha256=SHA)
    assert (tmp_path / "c.npz").read_bytes() == CONTENT


def test_an_unknown_artifact_is_not_found(tmp_path):
    with pytest.raises(NotFound):
        client_for(ArtifactServer()).download_artifact("art_2", tmp_path / "a.npz")
    assert list(tmp_path.iterdir()) == []
