"""A response's writes handed to the socket together (issue 23, per-frame HTTP answers).

uvicorn's protocols write a response's head when the application sends
``http.response.start`` and each body piece when it sends it, every one of them at once
(uvloop's transports try the socket before they return). On loopback a write runs the
receiving side's TCP path in the writer's context and wakes the client: a one-frame mesh
answer woke the client once for the 0.3 kB head, which it read and went back to sleep for,
and again for the body. Sampled on the server (py-spy, the lean route with its synthesis
stubbed to 12 ms of memory streaming, ``benchmarks/http_overhead.py --busy 12``) the head's
write took as long as the 538 kB body's: 0.14 and 0.12 ms a call of the event loop's
0.5 ms outside the thread hand-off.

:class:`CoalescedWrites` wraps a connection's transport: what the protocol writes during one
iteration of the event loop is kept (references, no copy) and handed to the transport in
one ``writelines`` at the end of that iteration (``loop.call_soon``), which uvloop sends
with one vectored write. ``benchmarks/realtime.py --against`` (the level-1 PDM, a server of the
commit before beside one of this, frames interleaved; two runs, the host's speed moving by
40 % between them): a mesh frame 13.0 → 12.7 and 19.1 → 18.7 ms through the SDK, every mesh
variant 0.3–1.5 ms less, the server's CPU 0.2–1.3 ms less a frame; a maps frame (its answer
in a dozen pieces) 61.2 → 57.9 and 65.9 → 67.3 ms, within the runs' noise. Nothing waits
longer than the iteration it was written in, so a
streamed response (job events, downloads) goes out as before, piece by piece as the
application awaits between pieces. ``close`` hands over what is kept first. Only uvloop's
transports are wrapped (:func:`coalesced`): asyncio's own (the pure-Python h11 protocol's
plain loop) join the pieces of ``writelines`` into one copy, which costs a 9 MB maps
answer more than the wake-up it saves.
"""

from __future__ import annotations

import asyncio
from typing import Any

__all__ = ["CoalescedWrites", "coalesced"]


class CoalescedWrites:
    """A transport whose writes of one event-loop iteration go out together (module
    docstring); every other attribute is the wrapped transport's."""

    def __init__(self, transport: asyncio.Transport, loop: asyncio.AbstractEventLoop):
        self._transport = transport
        self._loop = loop
        self._kept: list[Any] = []

    def write(self, data: Any) -> None:
        if not data:
            return
        if not self._kept:
            self._loop.call_soon(self.flush)
        self._kept.append(data)

    def writelines(self, lines: Any) -> None:
        for data in lines:
            self.write(data)

    def flush(self) -> None:
        """Hand what was kept to the transport (nothing once it is closing)."""
        kept, self._kept = self._kept, []
        if not kept or self._transport.is_closing():
            return
        if len(kept) == 1:
            self._transport.write(kept[0])
        else:
            self._transport.writelines(kept)

    def close(self) -> None:
        self.flush()
        self._transport.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._transport, name)


def coalesced(transport: asyncio.Transport, loop: asyncio.AbstractEventLoop) -> Any:
    """``transport`` wrapped in :class:`CoalescedWrites` if it is uvloop's (whose
    ``writelines`` is one vectored write), else ``transport`` itself."""
    if type(transport).__module__.startswith("uvloop"):
        return CoalescedWrites(transport, loop)
    return transport
