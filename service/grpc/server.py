"""The real-time path of API.md: ``facesynth.v1.Synthesis/StreamSynthesize`` over gRPC.

A live motion-capture stream in, one detailed mesh (and the asked maps) out per frame, in
order. :class:`SynthesisServicer` does the work, with the model store injected as a
``load_model(model_id) -> model`` callable (any object with ``synthesize`` as
:meth:`service.methods.pdm.model.PdmModel.synthesize`); :func:`serve` starts a server.

Errors end the stream with a status (the full list is in ``synthesis.proto``), mapped once
by meaning (:data:`CODES`, the most specific class of :mod:`service.errors` winning):
``InvalidInput`` from the model → INVALID_ARGUMENT with its message, the frame named;
``load_model`` raising ``NotFound`` (or any ``LookupError``) → NOT_FOUND, ``Conflict``
(not ready) → FAILED_PRECONDITION, ``Unavailable`` → UNAVAILABLE, ``Corrupt`` → DATA_LOSS.

Each open stream holds one worker thread for its whole life; a server runs at most
``max_workers`` streams, and one more is refused with RESOURCE_EXHAUSTED rather than queued
behind a live stream.

A stream is pipelined (:class:`_Pipeline`): a reader thread takes MarkerFrames off the
stream and submits them, in order, to the server's synthesis threads, which synthesize and
encode the replies while the serving thread sends the earlier ones; the replies are handed to
gRPC in the frames' order. At most ``pipeline_depth`` frames of a stream are in flight (read
and their replies not yet handed to gRPC), beyond which the reader waits (and gRPC flow
control holds the client back). Errors come out in order too: frame n's INVALID_ARGUMENT ends
the stream after the replies of frames 0..n-1.

The synthesis threads are one pool of ``synthesis_threads`` per server, shared by its
streams: the synthesis slots of :mod:`service.app.threads` (one per core by default), against
which ``facesynth serve`` sizes the BLAS and compiled-kernel threads, so S frames at once
each get cores / S threads and the cores are not oversubscribed. ``facesynth serve`` passes
the process's pool (``synthesis``, :attr:`service.app.services.Services.synthesis`), whose
slots the HTTP syntheses take too: S at once over both transports, not S each. A frame's work releases the
GIL (NumPy and BLAS, SciPy's sparse products, the Numba kernels compiled ``nogil``), so
frames of one stream are synthesized side by side: with S = 2 on 2 cores the default depth,
S + 1, keeps both threads busy while one reply is sent. Each frame's result is that of
``model.synthesize`` on it alone, whatever thread runs it (the kernels' scratch arrays are
per thread), so the replies are the one-thread path's bit for bit. The replies are the
MeshFrames' serialized bytes, written straight from the result arrays on the synthesis thread
(:func:`~service.grpc.codec.reply_pieces`, one copy of each map; gRPC sends them as they are,
:func:`add_servicer`).
"""

from __future__ import annotations

import contextvars
import dataclasses
import ipaddress
import logging
import queue
import re
import threading
import time
from concurrent import futures
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Protocol, Sequence

import grpc
import numpy as np

from models_store.tenancy import Principal, TokenTable
from service.app.threads import SynthesisPool
from service.methods.kinds import takes
from service.grpc import codec
from service.grpc.facesynth.v1 import synthesis_pb2 as pb
from service.grpc.facesynth.v1 import synthesis_pb2_grpc as pb_grpc
from service.errors import (
    Conflict, Corrupt, FacesynthError, InsufficientStorage, InvalidInput, NotAcceptable, NotFound,
    PayloadTooLarge, Unavailable,
)
from models_store.errors import storage_error

log = logging.getLogger(__name__)

#: each meaning of :mod:`service.errors` → the status a stream ends with
CODES: dict[type[FacesynthError], grpc.StatusCode] = {
    InvalidInput: grpc.StatusCode.INVALID_ARGUMENT,
    NotAcceptable: grpc.StatusCode.INVALID_ARGUMENT,
    NotFound: grpc.StatusCode.NOT_FOUND,
    Conflict: grpc.StatusCode.FAILED_PRECONDITION,
    PayloadTooLarge: grpc.StatusCode.RESOURCE_EXHAUSTED,
    Corrupt: grpc.StatusCode.DATA_LOSS,
    Unavailable: grpc.StatusCode.UNAVAILABLE,
    InsufficientStorage: grpc.StatusCode.RESOURCE_EXHAUSTED,
}


def code_of(error: BaseException) -> grpc.StatusCode:
    """The status for ``error`` by meaning (a bare ``LookupError`` is NOT_FOUND; anything
    else unknown is INTERNAL)."""
    for cls in type(error).__mro__:
        if cls in CODES:
            return CODES[cls]
    return grpc.StatusCode.NOT_FOUND if isinstance(error, LookupError) else grpc.StatusCode.INTERNAL
DEFAULT_PORT = 50051


def default_depth(synthesis_threads: int) -> int:
    """Frames of a stream in flight at most by default (read off the stream, reply not yet
    handed to gRPC): one on each synthesis thread and the one being sent."""
    return int(synthesis_threads) + 1


class StreamModel(Protocol):
    """What a stream needs of a model: :meth:`PdmModel.synthesize`'s signature. Options it
    may also take (:func:`takes`; :meth:`PdmModel.synthesize` takes both): ``half`` — passed
    ``half=True`` on a half-precision stream, the model writes its maps as float16 itself
    (any other model's float32 maps are converted when the reply is written); ``confidence``
    — passed ``confidence=False``, the model does not compute the confidence a MeshFrame
    does not carry."""

    def synthesize(self, markers: np.ndarray, outputs: Sequence[str] = ...,
                   clamp: bool = ...) -> dict[str, np.ndarray]: ...


#: the injected model store: model id → model; raises for unknown or not-ready models
LoadModel = Callable[[str], StreamModel]


class StreamError(Exception):
    """Ends a stream with a gRPC status code and a message for the client."""

    def __init__(self, code: grpc.StatusCode, details: str):
        super().__init__(details)
        self.code = code
        self.details = details


@dataclass(frozen=True)
class _Stream:
    """What the first MarkerFrame fixes for the whole stream."""

    model_id: str
    model: StreamModel
    outputs: tuple[str, ...]
    clamp: bool
    half: bool = False
    #: the keyword options ``synthesize`` is called with (:func:`stream_options`)
    options: dict = dataclasses.field(default_factory=dict)

    def reply(self, msg: pb.MarkerFrame, where: str, start: float, first: bool) -> bytes:
        """Synthesize and encode one frame: the serialized MeshFrame (``start``: when it was
        read; latency_ms is the time until the reply's last copy into the message)."""
        try:
            markers = codec.decode_markers(msg)
            result = self.model.synthesize(markers[None], list(self.outputs), self.clamp, **self.options)
        except InvalidInput as e:
            raise _invalid(_name_frame(str(e), where)) from None
        pieces = codec.reply_pieces(result, self.outputs, msg.frame, faces=first, half=self.half)
        return codec.join_reply(pieces, (time.perf_counter() - start) * 1e3)

    def check(self, msg: pb.MarkerFrame, where: str) -> None:
        """Raise INVALID_ARGUMENT if a later message changes what the first one fixed."""
        if msg.model_id and msg.model_id != self.model_id:
            raise _invalid(f"{where}: model_id '{msg.model_id}' differs from the stream's "
                           f"'{self.model_id}' (one model per stream)")
        if msg.outputs and tuple(dict.fromkeys(msg.outputs)) != self.outputs:
            raise _invalid(f"{where}: outputs {list(msg.outputs)} differ from the first message's "
                           f"{list(self.outputs)} (outputs are fixed per stream)")
        if msg.HasField("clamp") and msg.clamp != self.clamp:
            raise _invalid(f"{where}: clamp {msg.clamp} differs from the first message's {self.clamp}")
        if msg.HasField("half") and msg.half != self.half:
            raise _invalid(f"{where}: half {msg.half} differs from the first message's {self.half}")


def stream_options(model: StreamModel, half: bool) -> dict:
    """The keyword options a stream calls ``model.synthesize`` with, those it takes
    (:func:`takes`): ``half=True`` on a half-precision stream, ``confidence=False`` (a
    MeshFrame has no confidence)."""
    options = {"half": True} if half and takes(model, "half") else {}
    if takes(model, "confidence"):
        options["confidence"] = False
    return options


def _where(msg: pb.MarkerFrame, index: int) -> str:
    return f"frame {msg.frame}" + (f" (message {index} of the stream)" if msg.frame != index else "")


class _Pipeline:
    """One stream's frames in flight: a reader thread submitting them to the server's
    synthesis threads, and the replies in order (iterate on the serving thread; :meth:`close`
    when done).

    Parameters
    ----------
    stream : the stream opened from its first message
    first : that first message; requests : the rest of the stream
    depth : frames in flight at most (>= 1)
    synthesis : the executor that synthesizes and encodes the frames (any number of threads:
                the replies are taken in submission order)
    """

    _END = object()

    def __init__(self, stream: _Stream, first: pb.MarkerFrame,
                 requests: Iterator[pb.MarkerFrame], depth: int, synthesis: futures.Executor):
        self.stream, self.first, self.requests = stream, first, requests
        self.slots = threading.Semaphore(max(1, int(depth)))
        self.items: queue.SimpleQueue = queue.SimpleQueue()
        self.stopped = threading.Event()
        self.synthesis = synthesis
        self.submitting = threading.Lock()        # no frame is submitted once close() ran
        # the reader and the synthesis threads run in copies of the call's context (the
        # tenant scope of the registry is a context variable)
        self.reader = threading.Thread(target=contextvars.copy_context().run,
                                       args=(self._read,), name="facesynth-grpc-reader",
                                       daemon=True)
        self.reader.start()

    def _slot(self) -> bool:
        while not self.slots.acquire(timeout=0.1):
            if self.stopped.is_set():
                return False
        return not self.stopped.is_set()

    def _read(self) -> None:
        msg, index = self.first, 0
        try:
            while self._slot():
                if index > 0:
                    msg = next(self.requests, None)
                    if msg is None:
                        break
                where = _where(msg, index)
                if index > 0:
                    self.stream.check(msg, where)
                start = time.perf_counter()
                with self.submitting:
                    if self.stopped.is_set():
                        break
                    self.items.put(self.synthesis.submit(contextvars.copy_context().run,
                                                         self.stream.reply, msg, where, start,
                                                         index == 0))
                index += 1
        except BaseException as error:             # a changed stream, or the call ended
            self.items.put(error)
        self.items.put(self._END)

    def __iter__(self) -> Iterator[bytes]:
        while True:
            item = self.items.get()
            if item is self._END:
                return
            if isinstance(item, BaseException):
                raise item
            reply = item.result()
            yield reply
            self.slots.release()                   # gRPC took the reply: one more may come

    def close(self) -> None:
        """Stop reading, and cancel the frames submitted and not yet started (one running
        finishes on its thread, its reply dropped)."""
        with self.submitting:
            self.stopped.set()
        while True:
            try:
                item = self.items.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, futures.Future):
                item.cancel()


class SynthesisServicer(pb_grpc.SynthesisServicer):
    """``StreamSynthesize``: one MeshFrame per MarkerFrame, in order.

    Parameters
    ----------
    load_model : model id → model with ``synthesize(markers (F,M,3), outputs, clamp) ->
                 dict`` as :meth:`~service.methods.pdm.model.PdmModel.synthesize`; called
                 once per stream (and then from several threads at once). Raises
                 ``KeyError`` / a ``NotFound`` for an unknown id, a ``NotReady`` /
                 ``Conflict`` for a model that cannot synthesize yet.
    depth : int or None          frames of a stream in flight at most (None:
                                 :func:`default_depth` of the synthesis threads)
    synthesis_threads : int or None   frames synthesized at once, over all streams (None:
                                 :func:`~service.app.threads.synthesis_slots`, one per core)
    synthesis : SynthesisPool or None   the process's synthesis slots to synthesize in
                                 (shared with the HTTP syntheses; replaces
                                 ``synthesis_threads``); None: a pool of the servicer's own
    """

    def __init__(self, load_model: LoadModel, depth: int | None = None,
                 synthesis_threads: int | None = None, synthesis: SynthesisPool | None = None):
        self._load_model = load_model
        # idle threads end when the pool is collected
        self._synthesis = synthesis if synthesis is not None else SynthesisPool(synthesis_threads)
        self.synthesis_threads = self._synthesis.limit
        self.depth = int(depth) if depth else default_depth(self.synthesis_threads)

    def StreamSynthesize(self, request_iterator: Iterable[pb.MarkerFrame],
                         context: grpc.ServicerContext) -> Iterator[bytes]:
        try:
            yield from self._replies(request_iterator)
        except StreamError as e:
            context.abort(e.code, e.details)
        except Exception as e:
            if not context.is_active():          # the client went away: nothing to answer
                return
            meaning = storage_error(e)           # a full or read-only disk, by meaning
            if meaning is not None:
                log.warning("StreamSynthesize: storage fault: %s", meaning)
                context.abort(code_of(meaning), str(meaning))
            log.exception("StreamSynthesize failed")
            context.abort(grpc.StatusCode.INTERNAL, "internal error while synthesizing (see the server log)")

    def _replies(self, requests: Iterable[pb.MarkerFrame]) -> Iterator[bytes]:
        requests = iter(requests)
        first = next(requests, None)
        if first is None:
            return
        pipeline = _Pipeline(self._open(first), first, requests, self.depth, self._synthesis)
        try:
            yield from pipeline
        finally:
            pipeline.close()

    def _open(self, first: pb.MarkerFrame) -> _Stream:
        """The stream's model, outputs and clamp from its first message."""
        if not first.model_id:
            raise _invalid("the first MarkerFrame of a stream must name a model_id")
        try:
            outputs = codec.check_outputs(first.outputs)
        except InvalidInput as e:
            raise _invalid(str(e)) from None
        clamp = first.clamp if first.HasField("clamp") else True
        model = self._load(first.model_id)
        half = first.HasField("half") and first.half
        return _Stream(first.model_id, model, outputs, clamp, half, stream_options(model, half))

    def _load(self, model_id: str) -> StreamModel:
        try:
            return self._load_model(model_id)
        except (FacesynthError, LookupError) as e:
            code = code_of(e)
            if code == grpc.StatusCode.NOT_FOUND:
                raise StreamError(code, f"model '{model_id}' not found") from e
            if code == grpc.StatusCode.FAILED_PRECONDITION:
                raise StreamError(code, f"model '{model_id}' cannot synthesize yet: {e}") from e
            if code == grpc.StatusCode.INTERNAL:
                raise
            raise StreamError(code, f"model '{model_id}': {e}") from e


def _invalid(details: str) -> StreamError:
    return StreamError(grpc.StatusCode.INVALID_ARGUMENT, details)


def _name_frame(message: str, where: str) -> str:
    """A model message about one frame, naming the stream's frame: the model is called
    with one frame at a time, so its "frame 0" is ``where``."""
    named, n = re.subn(r"^frame 0\b", where, message)
    return named if n else f"{where}: {message}"


# ---------------------------------------------------------------------- auth
class BearerTokenAuth(grpc.ServerInterceptor):
    """Refuses calls without ``authorization: Bearer <token>`` metadata naming one of
    ``tokens`` (UNAUTHENTICATED), and runs each authorized call scoped to its token's tenant
    (another tenant's model answers NOT_FOUND, as an unknown one). ``tokens`` are
    ``FACESYNTH_TOKENS`` entries (:mod:`models_store.tenancy`: digests only, constant-time)."""

    def __init__(self, tokens: Sequence[str]):
        if not tokens or not all(tokens):
            raise ValueError("BearerTokenAuth needs one or more non-empty tokens")
        self._table = TokenTable(tokens)

    def principal(self, metadata: Sequence[tuple[str, str | bytes]] | None) -> Principal | None:
        """The principal of the call's bearer token, or None."""
        for key, value in metadata or ():
            if key != "authorization" or not isinstance(value, str):
                continue
            scheme, _, token = value.partition(" ")
            if scheme.lower() == "bearer" and token.strip():
                found = self._table.authenticate(token.strip())
                if found is not None:
                    return found
        return None

    def authorized(self, metadata: Sequence[tuple[str, str | bytes]] | None) -> bool:
        """Whether the call metadata carries a valid bearer token."""
        return self.principal(metadata) is not None

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None:
            return handler
        principal = self.principal(handler_call_details.invocation_metadata)
        if principal is None:
            return _refusing(handler)
        return _scoped(handler, principal)


def _scoped(handler: grpc.RpcMethodHandler, principal: Principal) -> grpc.RpcMethodHandler:
    """``handler`` with its behaviour run with the registry scoped to ``principal``'s tenant
    (set on the serving thread for the call's duration, reset after it)."""
    from models_store.registry import acting_for

    kind = (("stream" if handler.request_streaming else "unary") + "_"
            + ("stream" if handler.response_streaming else "unary"))
    behavior = getattr(handler, kind)

    if handler.response_streaming:
        def run(request_or_iterator, context):
            with acting_for(principal.tenant, principal.scope):
                yield from behavior(request_or_iterator, context)
    else:
        def run(request_or_iterator, context):
            with acting_for(principal.tenant, principal.scope):
                return behavior(request_or_iterator, context)

    make = getattr(grpc, f"{kind}_rpc_method_handler")
    return make(run, request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer)


def _refusing(handler: grpc.RpcMethodHandler) -> grpc.RpcMethodHandler:
    """A handler of the same kind as ``handler`` that fails with UNAUTHENTICATED."""
    def refuse(request_or_iterator, context: grpc.ServicerContext):
        context.abort(grpc.StatusCode.UNAUTHENTICATED,
                      "missing or invalid token: send metadata 'authorization: Bearer <token>'")

    kind = (("stream" if handler.request_streaming else "unary") + "_"
            + ("stream" if handler.response_streaming else "unary"))
    make = getattr(grpc, f"{kind}_rpc_method_handler")
    return make(refuse, request_deserializer=handler.request_deserializer,
                response_serializer=handler.response_serializer)


# ---------------------------------------------------------------------- server
def is_loopback(host: str) -> bool:
    """Whether ``host`` ("localhost", "127.0.0.1", "::1", "[::1]", …) is a loopback address."""
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def create_server(load_model: LoadModel, max_workers: int = 4, tokens: Sequence[str] = (),
                  max_message_bytes: int = codec.MAX_MESSAGE_BYTES,
                  pipeline_depth: int | None = None,
                  synthesis_threads: int | None = None,
                  synthesis: SynthesisPool | None = None) -> grpc.Server:
    """A gRPC server with the Synthesis service, not yet bound or started.

    Parameters
    ----------
    load_model : see :class:`SynthesisServicer`
    max_workers : int         threads = streams served at once; more are refused
                              (RESOURCE_EXHAUSTED)
    tokens : bearer tokens; none: no authentication
    max_message_bytes : int   largest message received or sent, bytes (a reply with a
                              1024² normal map alone is 12 MiB)
    pipeline_depth : int      frames of a stream in flight at most (None: the synthesis
                              threads + 1; see the module docstring)
    synthesis_threads : int   frames synthesized at once over all streams (None: one per
                              core, :func:`~service.app.threads.synthesis_slots`; ``facesynth
                              serve`` passes ``max_concurrent_syntheses``, the count its BLAS
                              threads are sized against)
    synthesis : SynthesisPool   the synthesis slots to share (``facesynth serve``: the
                              process's, :attr:`~service.app.services.Services.synthesis`, which
                              the HTTP syntheses take too); None: ``synthesis_threads`` of its own
    """
    options = [("grpc.max_send_message_length", max_message_bytes),
               ("grpc.max_receive_message_length", max_message_bytes),
               ("grpc.so_reuseport", 0)]       # a port in use is an error, not shared
    server = grpc.server(futures.ThreadPoolExecutor(max_workers, thread_name_prefix="facesynth-grpc"),
                         interceptors=[BearerTokenAuth(tokens)] if tokens else None,
                         options=options, maximum_concurrent_rpcs=max_workers)
    add_servicer(SynthesisServicer(load_model, pipeline_depth, synthesis_threads, synthesis),
                 server)
    return server


def add_servicer(servicer: SynthesisServicer, server: grpc.Server) -> None:
    """``pb_grpc.add_SynthesisServicer_to_server`` with the replies sent as the servicer
    yields them: serialized MeshFrames (:func:`~service.grpc.codec.serialize_reply`)."""
    service = pb.DESCRIPTOR.services_by_name["Synthesis"]
    handlers = {"StreamSynthesize": grpc.stream_stream_rpc_method_handler(
        servicer.StreamSynthesize, request_deserializer=pb.MarkerFrame.FromString,
        response_serializer=codec.serialize_reply)}
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(service.full_name,
                                                                          handlers),))
    server.add_registered_method_handlers(service.full_name, handlers)


def serve(load_model: LoadModel, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
          max_workers: int = 4, *, tokens: Sequence[str] = (),
          max_message_bytes: int = codec.MAX_MESSAGE_BYTES,
          pipeline_depth: int | None = None,
          synthesis_threads: int | None = None,
          synthesis: SynthesisPool | None = None) -> grpc.Server:
    """Start a Synthesis server on ``host:port`` (plaintext) and return it.

    Stop it with ``server.stop(grace)``; ``server.wait_for_termination()`` blocks until then.
    As the HTTP API: without tokens it only listens on loopback (TLS belongs in front of
    it, e.g. the ingress proxy). Other parameters as :func:`create_server`.

    Raises
    ------
    ValueError  a non-loopback host without tokens
    RuntimeError  the address cannot be bound (e.g. the port is in use)
    """
    if not tokens and not is_loopback(host):
        raise ValueError(f"refusing to listen on {host} without tokens: "
                         "give tokens, or listen on loopback (127.0.0.1)")
    server = create_server(load_model, max_workers, tokens, max_message_bytes, pipeline_depth,
                           synthesis_threads, synthesis)
    address = f"[{host.strip('[]')}]:{port}" if ":" in host else f"{host}:{port}"
    if server.add_insecure_port(address) == 0:        # older grpcio returns 0, newer raise
        raise RuntimeError(f"cannot listen on {address}")
    server.start()
    return server
