"""Memory and time of the ``usd`` result format (:class:`service.jobs.frame_usd.FrameUsdWriter`)
for a level-0-sized mesh (11 248 vertices) and F frames of random float32 points, written in
16-frame chunks as the synthesis job writes them.

Reports, per F: the points' size, the anonymous (heap) and file-backed resident memory the
writer added when the stage is built and about to be exported (the moment both the stage and
the chunks' memory map are alive), and the time of ``finish``. The claim checked: the heap holds
the points once (the stage); the map's pages are file-backed and reclaimable.

    python benchmarks/usd_cache.py [F ...]      (default 600 1800)
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import service.io.usd as usd  # noqa: E402
from service.jobs.frame_usd import FrameUsdWriter  # noqa: E402

VERTICES, TRIANGLES, CHUNK = 11248, 22000, 16


def _rss() -> dict[str, float]:
    """RssAnon and RssFile of this process, MiB."""
    values = {}
    for line in open("/proc/self/status"):
        if line.startswith(("RssAnon", "RssFile")):
            key, value = line.split(":", 1)
            values[key] = int(value.split()[0]) / 1024
    return values


def measure(frames: int) -> dict[str, float]:
    seen: dict[str, float] = {}
    export = usd._export

    def measured_export(stage, path):
        seen.update(_rss())
        export(stage, path)

    usd._export = measured_export
    rng = np.random.default_rng(0)
    faces = rng.integers(0, VERTICES, size=(TRIANGLES, 3))
    try:
        with tempfile.TemporaryDirectory() as tmp:
            writer = FrameUsdWriter(Path(tmp), frames, rng.uniform(size=(VERTICES, 2)))
            before = _rss()
            for start in range(0, frames, CHUNK):
                count = min(CHUNK, frames - start)
                writer.write(start, {"faces": faces, "vertices": rng.normal(
                    size=(count, VERTICES, 3)).astype(np.float32)})
            t = time.perf_counter()
            size = writer.finish().stat().st_size
            seconds = time.perf_counter() - t
    finally:
        usd._export = export
    return {"frames": frames, "points": frames * VERTICES * 12 / 2**20,
            "anon": seen["RssAnon"] - before["RssAnon"], "file": seen["RssFile"] - before["RssFile"],
            "seconds": seconds, "usd": size / 2**20}


def main(argv: list[str]) -> None:
    print("| frames | points MiB | heap added MiB | file-backed added MiB | finish s | .usd MiB |")
    print("|---|---|---|---|---|---|")
    for frames in map(int, argv or ["600", "1800"]):
        r = measure(frames)
        print(f"| {r['frames']} | {r['points']:.0f} | {r['anon']:.0f} | {r['file']:.0f} | "
              f"{r['seconds']:.1f} | {r['usd']:.0f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
