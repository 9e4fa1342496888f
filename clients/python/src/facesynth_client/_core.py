"""The one implementation behind :class:`Client` and :class:`AsyncClient`.

Every operation is written once, as a generator that *yields effects* and receives their
results (a "sans-I/O" core):

- :class:`Send` — send an ``httpx.Request``, receive the ``httpx.Response`` (its body read,
  unless streaming was asked and the status is a success);
- :class:`Read` — the next chunk of a streamed response (``b""`` at its end);
- :class:`Close` — close a streamed response;
- :class:`Sleep` — wait (backoff, polling);
- :class:`Emit` — hand a value to the caller of an iterator (job events).

The sync client runs these generators with ``httpx.Client`` and ``time.sleep``, the async one
with ``httpx.AsyncClient`` and ``asyncio.sleep``: only the sending differs. Request building,
retries with backoff, problem+json mapping, the event-stream parser, waiting for jobs and
resumable downloads live here.
"""

from __future__ import annotations

import dataclasses
import email.utils
import hashlib
import json as jsonlib
import os
import random
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Generator, Mapping

import httpx

from . import errors
from ._progress import make_reporter
from .types import Job

__all__ = ["Call", "Core", "Send", "Read", "Close", "Sleep", "Emit", "SSEParser", "job_id_of"]

#: methods that may be repeated without changing the result
IDEMPOTENT_METHODS = frozenset({"GET", "HEAD", "PUT", "DELETE", "OPTIONS"})
#: errors after which the request surely never reached the server (safe to resend any call)
_NOT_SENT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)
#: errors of a broken stream while reading a body
STREAM_ERRORS = (httpx.TransportError, httpx.StreamError)
DEFAULT_BASE_URL = "http://127.0.0.1:8000"
#: distinct (path, query) URLs kept parsed by :meth:`Core.request_url` (then it starts over)
URL_CACHE_MAX = 256


# ---------------------------------------------------------------------------- effects
@dataclass
class Send:
    request: httpx.Request
    stream: bool = False


@dataclass
class Read:
    response: httpx.Response


@dataclass
class Close:
    response: httpx.Response


@dataclass
class Sleep:
    seconds: float


@dataclass
class Emit:
    value: Any


Op = Generator[Any, Any, Any]


@dataclass
class Call:
    """One HTTP call: what to send and how it may be retried.

    ``idempotent`` defaults to the method's nature (GET, PUT, DELETE); a POST without side
    effects (synthesize, enhance, retime) sets it. Bodies are always bytes (or multipart of
    bytes), so every request can be resent.
    """

    method: str
    path: str
    params: Mapping[str, Any] | None = None
    json: Any = None
    content: bytes | None = None
    files: list[tuple[str, tuple[str, bytes, str]]] | None = None
    data: Mapping[str, Any] | None = None
    headers: Mapping[str, str] | None = None
    stream: bool = False
    idempotent: bool | None = None
    timeout: httpx.Timeout | None = None
    #: error statuses handed back as responses (not raised, not retried), e.g. /readyz's 503
    accept_statuses: tuple[int, ...] = ()

    @property
    def safe_to_repeat(self) -> bool:
        return self.idempotent if self.idempotent is not None else (
            self.method.upper() in IDEMPOTENT_METHODS)


def job_id_of(job: Any) -> str:
    """The job id of ``job``: a string, a :class:`Job`, or anything with ``job_id``
    (``ModelAccepted``, ``RigAccepted``, ``JobAccepted``)."""
    if isinstance(job, str):
        return job
    if isinstance(job, Job):
        return job.id
    value = getattr(job, "job_id", None)
    if isinstance(value, str):
        return value
    raise TypeError(f"expected a job id, a Job or an accepted job, got {type(job).__name__}")


def parse_retry_after(value: str | None, now: float | None = None) -> float | None:
    """Seconds to wait from a ``Retry-After`` header (delta-seconds or an HTTP date)."""
    if value is None:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=timezone.utc)
    current = now if now is not None else datetime.now(timezone.utc).timestamp()
    return max(0.0, when.timestamp() - current)


def api_error(response: httpx.Response) -> errors.ApiError:
    """The :class:`~facesynth_client.errors.ApiError` of an error response (its body read):
    the problem+json body, or one made of the status and the body's text."""
    problem: Any = None
    content_type = response.headers.get("content-type", "")
    if "json" in content_type:
        try:
            problem = response.json()
        except ValueError:
            problem = None
    if not isinstance(problem, dict):
        text = response.text[:1000] if response.content else ""
        problem = {"type": "about:blank", "title": response.reason_phrase,
                   "status": response.status_code, "detail": text}
    problem.setdefault("status", response.status_code)
    cls = errors.error_for_status(response.status_code)
    return cls(problem, headers={k.lower(): v for k, v in response.headers.items()})


# ---------------------------------------------------------------------------- SSE
@dataclass
class ServerEvent:
    event: str = "message"
    data: str = ""
    id: str | None = None


class SSEParser:
    """Incremental ``text/event-stream`` parser: :meth:`feed` bytes, get complete events."""

    def __init__(self) -> None:
        self._buffer = b""
        self._event: str | None = None
        self._data: list[str] = []
        self._id: str | None = None

    def feed(self, chunk: bytes) -> list[ServerEvent]:
        self._buffer += chunk
        events: list[ServerEvent] = []
        while True:
            cut = min((i for i in (self._buffer.find(b"\n"), self._buffer.find(b"\r"))
                       if i >= 0), default=-1)
            if cut < 0:
                return events
            line = self._buffer[:cut].decode("utf-8", "replace")
            step = 2 if self._buffer[cut:cut + 2] == b"\r\n" else 1
            if self._buffer[cut:cut + 1] == b"\r" and cut + 1 == len(self._buffer):
                return events  # a lone CR at the end may be half of CRLF: wait for more
            self._buffer = self._buffer[cut + step:]
            event = self._line(line)
            if event is not None:
                events.append(event)

    def _line(self, line: str) -> ServerEvent | None:
        if line == "":
            if not self._data and self._event is None:
                return None
            event = ServerEvent(self._event or "message", "\n".join(self._data), self._id)
            self._event, self._data = None, []
            return event
        if line.startswith(":"):
            return None
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "event":
            self._event = value
        elif name == "data":
            self._data.append(value)
        elif name == "id":
            self._id = value
        return None


# ---------------------------------------------------------------------------- the core
@dataclass
class Core:
    """Configuration and the effect-yielding operations shared by both clients.

    Parameters
    ----------
    base_url : str                  the server, e.g. ``http://127.0.0.1:8000``
    token : str or None             bearer token
    timeout : httpx.Timeout         per request
    max_retries : int               retries after the first attempt (0: none)
    backoff : float                 base of the exponential backoff, seconds
    backoff_max : float             cap of one backoff sleep, seconds
    poll_interval : float           seconds between polls when waiting without events
    build_request : callable        ``httpx.Client.build_request`` (or the async one's)
    random : callable               ``() -> [0,1)``, the jitter (tests make it fixed)
    clock : callable                monotonic seconds
    """

    base_url: str
    token: str | None
    timeout: httpx.Timeout
    max_retries: int
    backoff: float
    backoff_max: float
    poll_interval: float
    build_request: Callable[..., httpx.Request]
    headers: Mapping[str, str] = field(default_factory=dict)
    random: Callable[[], float] = random.random
    clock: Callable[[], float] = time.monotonic
    _urls: dict = field(default_factory=dict, repr=False, compare=False)

    # ------------------------------------------------------------------ sending
    def url(self, path: str) -> str:
        return self.base_url.rstrip("/") + "/" + path.lstrip("/")

    def request_url(self, path: str, params: Mapping[str, Any] | None) -> httpx.URL:
        """The URL of ``path`` with the query ``params`` (None values left out), parsed once
        per distinct pair: a per-frame call repeats the same one, and httpx would parse the
        string twice per request (0.07 ms of the SDK's ~0.3 ms a one-frame synthesis)."""
        items = tuple((k, v) for k, v in (params or {}).items() if v is not None)
        key = (path, items)
        try:
            url = self._urls.get(key)
        except TypeError:                       # an unhashable value (a list): not kept
            key = url = None
        if url is None:
            url = httpx.URL(self.url(path), params=dict(items) or None)
            if key is not None:
                if len(self._urls) >= URL_CACHE_MAX:
                    self._urls.clear()
                self._urls[key] = url
        return url

    def build(self, call: Call) -> httpx.Request:
        headers = {"Accept": "application/json, application/problem+json;q=0.9, */*;q=0.5",
                   **self.headers, **(call.headers or {})}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        return self.build_request(call.method, self.request_url(call.path, call.params),
                                  json=call.json, content=call.content, files=call.files,
                                  data=call.data, headers=headers,
                                  timeout=call.timeout or self.timeout)

    def backoff_delay(self, attempt: int) -> float:
        """Full jitter: uniform in [0, min(backoff_max, backoff · 2^attempt))."""
        return self.random() * min(self.backoff_max, self.backoff * (2 ** attempt))

    def send(self, call: Call) -> Op:
        """Send ``call``, retrying connection errors, timeouts and 503s; return the
        response or raise the mapped :class:`~facesynth_client.errors.FacesynthError`.

        Retries: up to ``max_retries`` more attempts, sleeping the full-jitter backoff (or
        the 503's ``Retry-After``). A connection that could not be opened is retried for
        every call (the server never saw it); other transport errors only for idempotent
        calls; a 503 for every call (the server refused it before doing anything). Other
        4xx/5xx are never retried.
        """
        attempt = 0
        while True:
            request = self.build(call)
            try:
                response = yield Send(request, call.stream)
            except httpx.TransportError as error:
                if attempt < self.max_retries and (call.safe_to_repeat
                                                   or isinstance(error, _NOT_SENT)):
                    yield Sleep(self.backoff_delay(attempt))
                    attempt += 1
                    continue
                raise errors.TransportError(
                    f"{call.method} {request.url}: {type(error).__name__}: {error}") from error
            if response.status_code in call.accept_statuses:
                return response
            if response.status_code == 503 and attempt < self.max_retries:
                delay = parse_retry_after(response.headers.get("retry-after"))
                yield Close(response)
                yield Sleep(self.backoff_delay(attempt) if delay is None else delay)
                attempt += 1
                continue
            if response.status_code >= 400:
                yield Close(response)
                raise api_error(response)
            return response

    def call_json(self, call: Call, parse: Callable[[Any], Any] | None = None) -> Op:
        """Send ``call`` and parse its JSON body (``parse(body)``; the body if None)."""
        response = yield from self.send(call)
        body = response.json() if response.content else None
        return parse(body) if parse is not None else body

    def call_items(self, call: Call, parse: Callable[[Any], Any]) -> Op:
        """A listing's items (``{"items": [...]}``), each parsed by ``parse``, from every page.

        A server that pages a listing answers with a ``next_cursor``; it is sent back as
        ``cursor`` until the server gives none. A listing without ``next_cursor`` is one
        page, so servers that page and servers that do not are both read whole.
        """
        params = dict(call.params or {})
        out: list = []
        seen: set[str] = set()
        while True:
            body = yield from self.call_json(dataclasses.replace(call, params=params))
            out.extend(parse(item) for item in body["items"])
            cursor = body.get("next_cursor")
            if not cursor:
                return out
            if cursor in seen:
                raise errors.TransportError(f"{call.method} {call.path}: the server repeated "
                                            f"the page cursor {cursor!r}")
            seen.add(cursor)
            params = {**params, "cursor": cursor}

    def call_bytes(self, call: Call) -> Op:
        response = yield from self.send(call)
        return response.content

    def call_text(self, call: Call) -> Op:
        response = yield from self.send(call)
        return response.text

    def call_empty(self, call: Call) -> Op:
        yield from self.send(call)
        return None

    def call_accepted(self, call: Call, parse: Callable[[Any], Any]) -> Op:
        """A 202 answer: its JSON parsed, with ``location`` from the header when the
        result type has one."""
        response = yield from self.send(call)
        body = dict(response.json())
        if "location" not in body and response.headers.get("location"):
            body["location"] = response.headers["location"]
        return parse(body)

    # ------------------------------------------------------------------ jobs
    def get_job(self, job_id: str) -> Op:
        return (yield from self.call_json(Call("GET", f"/v1/jobs/{job_id}"), Job.from_json))

    def _stream_timeout(self, deadline: float | None) -> httpx.Timeout:
        read = self.timeout.read
        if deadline is not None:
            remaining = max(0.05, deadline - self.clock())
            read = remaining if read is None else min(read, remaining)
        return httpx.Timeout(self.timeout.connect, read=read, write=self.timeout.write,
                             pool=self.timeout.pool)

    def follow_events(self, job_id: str, on_job: Callable[[Job], None] | None,
                      deadline: float | None = None) -> Op:
        """Read ``GET /v1/jobs/{id}/events`` until the job ends; each job state goes to
        ``on_job`` or, if it is None, is emitted (:class:`Emit`). Returns the last job seen
        (None if the stream ended before any)."""
        call = Call("GET", f"/v1/jobs/{job_id}/events", stream=True,
                    headers={"Accept": "text/event-stream"},
                    timeout=self._stream_timeout(deadline))
        response = yield from self.send(call)
        parser, last = SSEParser(), None
        while True:
            try:
                chunk = yield Read(response)
            except STREAM_ERRORS as error:
                raise errors.TransportError(f"the event stream of job {job_id} broke: "
                                            f"{type(error).__name__}: {error}") from error
            if not chunk:
                yield Close(response)
                return last
            for event in parser.feed(chunk):
                if event.event not in ("progress", "end", "message") or not event.data:
                    continue
                job = Job.from_json(jsonlib.loads(event.data))
                last = job
                if on_job is None:
                    yield Emit(job)
                else:
                    on_job(job)
                if job.done or event.event == "end":
                    yield Close(response)
                    return job

    def wait(self, job: Any, timeout: float | None = None, progress: Any = False,
             poll_interval: float | None = None, events: bool = True) -> Op:
        """Follow a job until it ends: the event stream, falling back to polling when the
        stream fails. Returns the succeeded :class:`Job`; raises ``JobFailed``,
        ``JobCancelled`` or ``WaitTimeout``."""
        job_id = job_id_of(job)
        interval = self.poll_interval if poll_interval is None else poll_interval
        deadline = None if timeout is None else self.clock() + timeout
        show, close = make_reporter(progress, job_id)
        shown: list[tuple] = []

        def report(state: Job) -> None:  # each distinct state once
            key = (state.status, state.progress, state.stage)
            if not shown or shown[-1] != key:
                shown[:] = [key]
                try:
                    show(state)
                except Exception as error:  # the caller's: not a stream failure
                    raise _CallbackError(error) from error

        last: Job | None = job if isinstance(job, Job) else None
        use_events = events
        try:
            while True:
                if last is not None and last.done:
                    break
                if deadline is not None and self.clock() >= deadline:
                    raise errors.WaitTimeout(
                        f"job {job_id} did not end within {timeout} s"
                        + (f" (it is {last.status}, {last.progress:.0%})" if last else ""), last)
                if use_events:
                    try:
                        seen = yield from self.follow_events(job_id, report, deadline)
                    except (errors.NotFound, errors.Unauthorized, errors.Forbidden,
                            _CallbackError):
                        raise
                    except (errors.FacesynthError, *STREAM_ERRORS, ValueError):
                        seen = None  # the stream failed: poll from now on
                    if seen is not None:
                        last = seen
                    if last is None or not last.done:
                        use_events = False
                    continue
                last = yield from self.get_job(job_id)
                report(last)
                if not last.done:
                    pause = interval if deadline is None else max(
                        0.0, min(interval, deadline - self.clock()))
                    yield Sleep(pause)
        except _CallbackError as wrapped:
            raise wrapped.error from None
        finally:
            close()
        if last.status == "failed":
            raise errors.JobFailed(last)
        if last.status == "cancelled":
            raise errors.JobCancelled(last)
        return last

    # ------------------------------------------------------------------ downloads
    def download(self, path: str, dest: str | os.PathLike, *, params: Mapping[str, Any] | None = None,
                 expected_sha256: str | None = None, resume: bool = True) -> Op:
        """Stream ``GET path`` into ``dest`` atomically: into ``<dest>.part`` first, renamed
        once complete and checked (``Content-Length``; the sha256 against
        ``expected_sha256`` or a sha256 ETag). A partial file left by an interrupted
        download is resumed with ``Range``/``If-Range``; a connection lost mid-transfer is
        resumed the same way (up to ``max_retries`` times)."""
        target = Path(dest)
        target.parent.mkdir(parents=True, exist_ok=True)
        part = target.with_name(target.name + ".part")
        tag_file = target.with_name(target.name + ".part.etag")
        attempt = 0
        while True:
            offset = part.stat().st_size if (resume and part.exists()) else 0
            etag = tag_file.read_text().strip() if (offset and tag_file.exists()) else None
            headers = {"Accept": "*/*"}
            if offset and etag:
                headers.update({"Range": f"bytes={offset}-", "If-Range": etag})
            call = Call("GET", path, params=params, headers=headers, stream=True)
            try:
                response = yield from self.send(call)
            except errors.RangeNotSatisfiable:
                part.unlink(missing_ok=True)
                tag_file.unlink(missing_ok=True)
                continue
            partial = response.status_code == 206
            if not partial:
                offset = 0
            etag = response.headers.get("etag")
            if etag:
                tag_file.write_text(etag)
            total = None
            if partial:
                content_range = response.headers.get("content-range", "")
                start = content_range.split(" ")[-1].split("-")[0]
                if not start.isdigit() or int(start) != offset:
                    yield Close(response)
                    part.unlink(missing_ok=True)
                    continue
                size = content_range.rsplit("/", 1)[-1]
                total = int(size) if size.isdigit() else None
            elif response.headers.get("content-length", "").isdigit():
                total = int(response.headers["content-length"])
            try:
                with open(part, "ab" if partial else "wb") as file:
                    while True:
                        chunk = yield Read(response)
                        if not chunk:
                            break
                        file.write(chunk)
            except STREAM_ERRORS as error:
                yield Close(response)
                if resume and attempt < self.max_retries:
                    yield Sleep(self.backoff_delay(attempt))
                    attempt += 1
                    continue
                raise errors.TransportError(f"download of {path} broke: {error}") from error
            yield Close(response)
            size = part.stat().st_size
            if total is not None and size != total:
                if resume and attempt < self.max_retries:
                    attempt += 1
                    continue
                raise errors.TransportError(f"download of {path}: got {size} of {total} bytes")
            digest = _sha256(part)
            tag = (etag or "").removeprefix("W/").strip('"').lower()
            wanted = (expected_sha256 or "").lower() or (
                tag if len(tag) == 64 and all(c in "0123456789abcdef" for c in tag) else None)
            if wanted and digest != wanted:
                part.unlink(missing_ok=True)
                tag_file.unlink(missing_ok=True)
                raise errors.IntegrityError(f"download of {path}: sha256 {digest} does not "
                                            f"match the expected {wanted}")
            os.replace(part, target)
            tag_file.unlink(missing_ok=True)
            return target


class _CallbackError(Exception):
    """An exception of the caller's progress callback, carried through :meth:`Core.wait`'s
    stream-failure handling untouched."""

    def __init__(self, error: Exception):
        super().__init__(str(error))
        self.error = error


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()

