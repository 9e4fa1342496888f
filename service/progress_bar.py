"""A progress display for long work (building the sample actor, training, synthesis jobs),
driven by ``update(fraction, stage)`` callbacks and drawn on stderr.

On a terminal it is a tqdm bar redrawn in place. Anywhere else (a log file, a CI job, a pipe)
a redrawn bar would be one very long line of carriage returns, so it writes occasional plain
lines instead: one when the stage changes or the progress has advanced by
:data:`LINE_STEP` since the last line, and one at the end::

    pdm train:   0% queued
    pdm train:  10% medium scale
    pdm train: 100% done

Used by the ``facesynth`` command line (``service.cli``, ``service.client_cli``) and the demo.
"""

from __future__ import annotations

import sys
from typing import Callable, TextIO

__all__ = ["progress_bar", "job_progress", "LINE_STEP"]

#: progress (a fraction) between two plain lines when stderr is not a terminal
LINE_STEP = 0.1

Update = Callable[[float, str], None]


def _is_terminal(stream: TextIO) -> bool:
    isatty = getattr(stream, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # a closed stream
        return False


def progress_bar(description: str, stream: TextIO | None = None,
                 terminal: bool | None = None) -> Update:
    """``update(fraction, stage)`` drawing the progress of ``description`` on ``stream``.

    Parameters
    ----------
    description : str          what is in progress, e.g. ``"pdm train"`` or a job id
    stream : text stream       default ``sys.stderr``
    terminal : bool, optional  draw a tqdm bar (True) or plain lines (False); default: whether
                               ``stream`` is a terminal

    Returns
    -------
    update : callable ``(fraction, stage)``; fraction in [0, 1] (clamped), the display ends
             at 1
    """
    stream = stream if stream is not None else sys.stderr
    if terminal is None:
        terminal = _is_terminal(stream)
    return _tqdm_bar(description, stream) if terminal else _line_bar(description, stream)


def _tqdm_bar(description: str, stream: TextIO) -> Update:
    from tqdm import tqdm

    bar = tqdm(total=100, desc=description, unit="%", file=stream,
               bar_format="{l_bar}{bar}| {n:.0f}% {postfix}")
    closed = False

    def update(fraction: float, stage: str) -> None:
        nonlocal closed
        if closed:
            return
        fraction = min(max(float(fraction), 0.0), 1.0)
        bar.n = round(100 * fraction, 1)
        bar.set_postfix_str(stage)
        bar.refresh()
        if fraction >= 1.0:
            bar.close()
            closed = True

    return update


def _line_bar(description: str, stream: TextIO) -> Update:
    last: list = []          # [fraction, stage] of the last line written

    def update(fraction: float, stage: str) -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        if last and last[0] >= 1.0:
            return
        if (not last or stage != last[1] or fraction - last[0] >= LINE_STEP - 1e-9
                or fraction >= 1.0):
            stream.write(f"{description}: {fraction * 100:3.0f}% {stage}\n")
            stream.flush()
            last[:] = [fraction, stage]

    return update


def job_progress(label: str, stream: TextIO | None = None,
                 terminal: bool | None = None) -> Callable[[object], None]:
    """A ``progress`` callback for the SDK's ``client.wait``: each job state (``.progress``,
    ``.stage``, ``.status``) drawn by :func:`progress_bar`."""
    update = progress_bar(label, stream, terminal)
    return lambda job: update(job.progress, job.stage or job.status)
