"""The clients: :class:`Client` (sync) and :class:`AsyncClient` (async).

Both hold the same resources, one module each under :mod:`facesynth_client.resources` —
``client.actors``, ``client.clips``, ``client.rigs``, ``client.models``, ``client.synthesis``,
``client.jobs``, ``client.artifacts``, ``client.tracking``, ``client.bone_rigs``, ``client.scans`` — and differ only in how they run an
operation of :mod:`facesynth_client._core`: ``Client`` sends its requests with
``httpx.Client`` and returns the result, ``AsyncClient`` with ``httpx.AsyncClient`` and returns
an awaitable (iterators are async iterators).

A few resource methods are also reachable on the client itself (:data:`SHORTCUTS`:
``client.wait`` is ``client.jobs.wait``, ``client.synthesize`` is
``client.synthesis.synthesize``, ...): the same bound method, not a second implementation.

Examples
--------
>>> import numpy as np
>>> from facesynth_client import Client
>>> with Client("http://127.0.0.1:8000") as fs:                        # doctest: +SKIP
...     actor = fs.actors.create("Ada")
...     fs.actors.upload_neutral(actor.id, "ada_neutral.obj")
...     fs.actors.set_markers(actor.id, {"FH1": 812, "FH2": 1304, "NOSE": 77})
...     clip = fs.clips.upload(actor.id, vertices=frames, markers=markers, fps=60)
...     accepted = fs.models.train(actor.id, "pdm", [clip.clip_id])
...     fs.wait(accepted, progress=True)
...     out = fs.synthesize(accepted.model_id, markers[:2])
...     out["vertices"].shape
(2, 40962, 3)
"""

from __future__ import annotations

import abc
import asyncio
import inspect
import os
import time
from typing import Any, Callable, Mapping

import httpx

from ._core import Call, Close, Core, DEFAULT_BASE_URL, Emit, Op, Read, Send, Sleep
from .resources import (Actors, Artifacts, BoneRigs, Clips, Jobs, Models, Rigs, Scans,
                        Synthesis,
                        Tracking)
from .transport import OnePieceTransport
from .types import Readiness

__all__ = ["Client", "AsyncClient", "SHORTCUTS"]

#: the default timeout: 60 s to read/write, 10 s to connect
DEFAULT_TIMEOUT = httpx.Timeout(60.0, connect=10.0)
#: client attribute → (resource, method): the resource methods also reachable on the client
SHORTCUTS = {
    "wait": ("jobs", "wait"),
    "cancel": ("jobs", "cancel"),
    "download_artifact": ("artifacts", "download"),
    "synthesize": ("synthesis", "synthesize"),
    "enhance": ("synthesis", "enhance"),
    "retime": ("synthesis", "retime"),
}


def unbind(response: httpx.Response) -> None:
    """Break httpx's reference cycle of a read and closed ``response``: its client sets
    ``response.stream`` to a stream bound to the response itself, so without this the
    response and its body are freed only by the next cyclic garbage collection, several
    calls later, not when the SDK and the caller drop them. A per-frame maps answer (9.1 MB)
    then lingers while the next ones are read into fresh memory, whose every page faults in
    (measured: 2,225 page faults an answer; none with the cycle broken). The content stays
    readable (``response.content``)."""
    response.stream = httpx.ByteStream(b"")


def _timeout(value: float | httpx.Timeout | None) -> httpx.Timeout:
    if isinstance(value, httpx.Timeout):
        return value
    return DEFAULT_TIMEOUT if value is None else httpx.Timeout(value)


class _Shortcut:
    """``client.<name>``: the bound method ``client.<resource>.<method>`` itself, so a
    shortcut has no code or documentation of its own (``Client.wait`` is ``Jobs.wait``)."""

    def __init__(self, resource: str, method: str, owner: type):
        self.resource, self.method = resource, method
        self.function = getattr(owner, method)

    def __get__(self, client: Any, owner: type | None = None) -> Any:
        if client is None:
            return self.function
        return getattr(getattr(client, self.resource), self.method)


class _Api(abc.ABC):
    """What :class:`Client` and :class:`AsyncClient` share: configuration, the resources and
    the service routes (health, readiness, metrics). Subclasses supply ``_run`` (and
    ``_iterate``)."""

    #: the resource classes, by attribute
    RESOURCES = {"actors": Actors, "clips": Clips, "rigs": Rigs, "models": Models,
                 "synthesis": Synthesis, "tracking": Tracking, "bone_rigs": BoneRigs,
                 "jobs": Jobs, "artifacts": Artifacts, "scans": Scans}

    def __init__(self, base_url: str | None, token: str | None, *, timeout: Any,
                 max_retries: int, backoff: float, backoff_max: float, poll_interval: float,
                 headers: Mapping[str, str] | None, http: Any, random: Callable[[], float] | None):
        client_base = str(getattr(http, "base_url", "") or "").rstrip("/")
        self.base_url: str = (base_url or client_base or os.environ.get("FACESYNTH_URL")
                              or DEFAULT_BASE_URL).rstrip("/")
        token = token if token is not None else os.environ.get("FACESYNTH_TOKEN") or None
        from . import __version__
        core_args: dict[str, Any] = {}
        if random is not None:
            core_args["random"] = random
        self._core = Core(
            base_url=self.base_url, token=token, timeout=_timeout(timeout),
            max_retries=int(max_retries), backoff=float(backoff), backoff_max=float(backoff_max),
            poll_interval=float(poll_interval), build_request=http.build_request,
            headers={"User-Agent": f"facesynth-client/{__version__}", **(headers or {})},
            **core_args)
        self.actors = Actors(self)
        self.clips = Clips(self)
        self.rigs = Rigs(self)
        self.models = Models(self)
        self.synthesis = Synthesis(self)
        self.tracking = Tracking(self)
        self.bone_rigs = BoneRigs(self)
        self.jobs = Jobs(self)
        self.artifacts = Artifacts(self)
        self.scans = Scans(self)

    @abc.abstractmethod
    def _run(self, op: Op) -> Any:
        """Run one request-building operation (sync: to its result; async: a coroutine)."""

    @abc.abstractmethod
    def _iterate(self, op: Op) -> Any:
        """Run a paged or streamed operation (sync: an iterator; async: an async iterator)."""

    @property
    def max_retries(self) -> int:
        return self._core.max_retries

    # ------------------------------------------------------------------ service routes
    def health(self) -> dict[str, Any]:
        """``GET /healthz``: ``{"status": "ok"}`` while the process serves requests."""
        return self._run(self._core.call_json(Call("GET", "/healthz")))

    def ready(self) -> Readiness:
        """``GET /readyz``: whether the database, the blob store and the queue are
        reachable (``.ready``), with each check; a 503 answer is returned, not raised."""
        return self._run(self._core.call_json(Call("GET", "/readyz", accept_statuses=(503,)),
                                              Readiness.from_json))

    def metrics(self) -> str:
        """``GET /metrics``: the Prometheus text exposition."""
        return self._run(self._core.call_text(Call("GET", "/metrics",
                                                   headers={"Accept": "text/plain"})))


for _name, (_resource, _method) in SHORTCUTS.items():
    setattr(_Api, _name, _Shortcut(_resource, _method, _Api.RESOURCES[_resource]))
del _name, _resource, _method


class Client(_Api):
    """The synchronous client.

    Parameters
    ----------
    base_url : str, optional    default ``$FACESYNTH_URL``, else ``http://127.0.0.1:8000``
                                (or the injected ``http_client``'s base URL)
    token : str, optional       bearer token, default ``$FACESYNTH_TOKEN``
    timeout : float or httpx.Timeout   per request (default 60 s, 10 s to connect)
    max_retries : int           retries of connection errors, timeouts and 503s (default 3);
                                other errors are never retried
    backoff : float             base of the exponential backoff with full jitter, seconds
    backoff_max : float         cap of one backoff sleep, seconds
    poll_interval : float       seconds between polls when waiting without events
    http_client : httpx.Client, optional   use this client (not closed by :meth:`close`)
    transport : httpx.BaseTransport, optional   transport of the client made here (e.g.
                                ``httpx.MockTransport`` in tests); default
                                :class:`~facesynth_client.transport.OnePieceTransport` (plain
                                ``http`` requests in one write, answers read in one piece;
                                ``https`` through httpx's own transport)
    sleep : callable, optional  ``sleep(seconds)`` for backoff and polling (default
                                ``time.sleep``; tests inject a recorder)
    headers : dict, optional    extra headers on every request

    Examples
    --------
    >>> with Client(token="s3cret") as fs:                                   # doctest: +SKIP
    ...     print(fs.health())
    {'status': 'ok'}
    """

    def __init__(self, base_url: str | None = None, token: str | None = None, *,
                 timeout: float | httpx.Timeout | None = None, max_retries: int = 3,
                 backoff: float = 0.5, backoff_max: float = 30.0, poll_interval: float = 1.0,
                 http_client: httpx.Client | None = None,
                 transport: httpx.BaseTransport | None = None,
                 sleep: Callable[[float], Any] | None = None,
                 headers: Mapping[str, str] | None = None,
                 random: Callable[[], float] | None = None):
        self._own = http_client is None
        transport = transport if transport is not None else OnePieceTransport()
        self._http = http_client if http_client is not None else httpx.Client(
            transport=transport, timeout=_timeout(timeout))
        #: the transport requests are handed to directly (:meth:`_send`), or None
        self._direct = transport if self._own and isinstance(transport, OnePieceTransport) else None
        self._sleep = sleep if sleep is not None else time.sleep
        super().__init__(base_url, token, timeout=timeout, max_retries=max_retries,
                         backoff=backoff, backoff_max=backoff_max, poll_interval=poll_interval,
                         headers=headers, http=self._http, random=random)

    def close(self) -> None:
        """Close the HTTP client made by this client (an injected one stays open)."""
        if self._own:
            self._http.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ------------------------------------------------------------------ the driver
    def _send(self, request: httpx.Request) -> httpx.Response:
        """``request``'s response, its body not yet read: from the SDK's own transport
        directly where this client made its httpx client with one (no auth, cookies, event
        hooks, redirects or proxy mounts to apply), else through ``httpx.Client.send``."""
        if self._direct is None or self._http.is_closed:
            return self._http.send(request, stream=True)
        response = self._direct.handle_request(request)
        response.request = request
        return response

    def _perform(self, effect: Any, streams: dict) -> Any:
        if isinstance(effect, Send):
            response = self._send(effect.request)
            if effect.stream and response.status_code < 400:
                streams[id(response)] = (response, response.iter_bytes())
            else:
                try:
                    response.read()
                finally:
                    response.close()
                    unbind(response)
            return response
        if isinstance(effect, Read):
            entry = streams.get(id(effect.response))
            if entry is not None:
                for chunk in entry[1]:
                    if chunk:
                        return chunk
            return b""
        if isinstance(effect, Close):
            entry = streams.pop(id(effect.response), None)
            if entry is not None:
                entry[0].close()
            return None
        if isinstance(effect, Sleep):
            self._sleep(effect.seconds)
            return None
        raise TypeError(f"unknown effect {effect!r}")

    def _steps(self, op: Op, result: list):
        """Run ``op``, yielding what it emits; its value is appended to ``result``."""
        streams: dict = {}
        value: Any = None
        error: BaseException | None = None
        try:
            while True:
                try:
                    effect = op.throw(error) if error is not None else op.send(value)
                except StopIteration as stop:
                    result.append(stop.value)
                    return
                value, error = None, None
                try:
                    if isinstance(effect, Emit):
                        yield effect.value
                    else:
                        value = self._perform(effect, streams)
                except Exception as exc:  # handed to the operation, which may handle it
                    error = exc
        finally:
            op.close()
            for response, _ in streams.values():
                response.close()

    def _run(self, op: Op) -> Any:
        result: list = []
        for _ in self._steps(op, result):
            pass
        return result[0]

    def _iterate(self, op: Op) -> Any:
        yield from self._steps(op, [])


class AsyncClient(_Api):
    """The asynchronous client: the same resources and methods as :class:`Client`, each
    returning an awaitable (:meth:`Jobs.events` an async iterator).

    Parameters are those of :class:`Client`, with an ``httpx.AsyncClient`` /
    ``httpx.AsyncBaseTransport`` and ``sleep`` an async (or plain) function.

    Examples
    --------
    >>> async with AsyncClient() as fs:                                    # doctest: +SKIP
    ...     actor = await fs.actors.create("Ada")
    ...     async for state in fs.jobs.events(job_id):
    ...         print(state.progress)
    """

    def __init__(self, base_url: str | None = None, token: str | None = None, *,
                 timeout: float | httpx.Timeout | None = None, max_retries: int = 3,
                 backoff: float = 0.5, backoff_max: float = 30.0, poll_interval: float = 1.0,
                 http_client: httpx.AsyncClient | None = None,
                 transport: httpx.AsyncBaseTransport | None = None,
                 sleep: Callable[[float], Any] | None = None,
                 headers: Mapping[str, str] | None = None,
                 random: Callable[[], float] | None = None):
        self._own = http_client is None
        self._http = http_client if http_client is not None else httpx.AsyncClient(
            transport=transport, timeout=_timeout(timeout))
        self._sleep = sleep if sleep is not None else asyncio.sleep
        super().__init__(base_url, token, timeout=timeout, max_retries=max_retries,
                         backoff=backoff, backoff_max=backoff_max, poll_interval=poll_interval,
                         headers=headers, http=self._http, random=random)

    async def aclose(self) -> None:
        """Close the HTTP client made by this client (an injected one stays open)."""
        if self._own:
            await self._http.aclose()

    async def __aenter__(self) -> "AsyncClient":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    # ------------------------------------------------------------------ the driver
    async def _perform(self, effect: Any, streams: dict) -> Any:
        if isinstance(effect, Send):
            response = await self._http.send(effect.request, stream=True)
            if effect.stream and response.status_code < 400:
                streams[id(response)] = (response, response.aiter_bytes())
            else:
                try:
                    await response.aread()
                finally:
                    await response.aclose()
                    unbind(response)
            return response
        if isinstance(effect, Read):
            entry = streams.get(id(effect.response))
            if entry is not None:
                while True:
                    try:
                        chunk = await entry[1].__anext__()
                    except StopAsyncIteration:
                        break
                    if chunk:
                        return chunk
            return b""
        if isinstance(effect, Close):
            entry = streams.pop(id(effect.response), None)
            if entry is not None:
                await entry[0].aclose()
            return None
        if isinstance(effect, Sleep):
            result = self._sleep(effect.seconds)
            if inspect.isawaitable(result):
                await result
            return None
        raise TypeError(f"unknown effect {effect!r}")

    async def _steps(self, op: Op, result: list):
        """Run ``op``, yielding what it emits; its value is appended to ``result``."""
        streams: dict = {}
        value: Any = None
        error: BaseException | None = None
        try:
            while True:
                try:
                    effect = op.throw(error) if error is not None else op.send(value)
                except StopIteration as stop:
                    result.append(stop.value)
                    return
                value, error = None, None
                try:
                    if isinstance(effect, Emit):
                        yield effect.value
                    else:
                        value = await self._perform(effect, streams)
                except Exception as exc:  # handed to the operation, which may handle it
                    error = exc
        finally:
            op.close()
            for response, _ in streams.values():
                await response.aclose()

    async def _run(self, op: Op) -> Any:
        result: list = []
        async for _ in self._steps(op, result):
            pass
        return result[0]

    async def _iterate(self, op: Op) -> Any:
        async for item in self._steps(op, []):
            yield item
