"""A progress display for :meth:`Client.wait`: on a terminal tqdm when it is importable,
else a tiny text bar on stderr (tqdm is not a dependency); off a terminal (a log file, CI) a
plain line every :data:`LINE_STEP` of progress and at each stage, never a redrawn bar."""

from __future__ import annotations

import sys
from typing import Any, Callable, TextIO


class TextBar:
    """``job_01… [#########-----------]  42% fine band`` redrawn in place on ``stream``."""

    def __init__(self, label: str, stream: TextIO | None = None, width: int = 30):
        self.label, self.width = label, width
        self.stream = stream if stream is not None else sys.stderr
        self._last: str | None = None

    def update(self, fraction: float, stage: str) -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        filled = int(round(fraction * self.width))
        line = (f"{self.label} [{'#' * filled}{'-' * (self.width - filled)}] "
                f"{fraction * 100:3.0f}% {stage}")[:120]
        if line != self._last:
            self.stream.write("\r" + line.ljust(len(self._last or "")))
            self.stream.flush()
            self._last = line

    def close(self) -> None:
        if self._last is not None:
            self.stream.write("\n")
            self.stream.flush()


#: progress between two plain lines off a terminal
LINE_STEP = 0.1


class LineBar:
    """``job_01…  42% fine band`` as a new line when the stage changes or the progress has
    advanced by :data:`LINE_STEP` (for logs: no carriage returns)."""

    def __init__(self, label: str, stream: TextIO | None = None):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self._last: tuple[float, str] | None = None

    def update(self, fraction: float, stage: str) -> None:
        fraction = min(max(float(fraction), 0.0), 1.0)
        last = self._last
        if last is None or stage != last[1] or fraction - last[0] >= LINE_STEP - 1e-9 or (
                fraction >= 1.0 > last[0]):
            self.stream.write(f"{self.label} {fraction * 100:3.0f}% {stage}\n")
            self.stream.flush()
            self._last = (fraction, stage)

    def close(self) -> None:
        pass


def _is_terminal(stream: TextIO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class TqdmBar:
    """The same interface on a ``tqdm`` bar (total 100)."""

    def __init__(self, label: str, tqdm: Any):
        self.bar = tqdm(total=100, desc=label, unit="%", leave=True,
                        bar_format="{desc} {bar} {n:.0f}% {postfix}")
        self.n = 0.0

    def update(self, fraction: float, stage: str) -> None:
        value = min(max(float(fraction), 0.0), 1.0) * 100
        if value > self.n:
            self.bar.update(value - self.n)
            self.n = value
        self.bar.set_postfix_str(stage, refresh=True)

    def close(self) -> None:
        self.bar.close()


def make_reporter(progress: Any, label: str) -> tuple[Callable[[Any], None], Callable[[], None]]:
    """``(report(job), close())`` for ``progress``: True (a bar on stderr), False/None
    (nothing) or a callable ``(job) -> None``."""
    if callable(progress):
        return progress, lambda: None
    if not progress:
        return (lambda job: None), (lambda: None)
    if not _is_terminal(sys.stderr):
        bar: Any = LineBar(label)
        return (lambda job: bar.update(job.progress, job.stage or job.status)), bar.close
    try:
        from tqdm import tqdm  # optional: used only if already installed
        bar = TqdmBar(label, tqdm)
    except Exception:
        bar = TextBar(label)
    return (lambda job: bar.update(job.progress, job.stage or job.status)), bar.close
