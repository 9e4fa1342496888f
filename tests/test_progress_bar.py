"""service.progress_bar: a redrawn bar on a terminal, occasional plain lines elsewhere."""

from __future__ import annotations

import io
from types import SimpleNamespace

from service.progress_bar import LINE_STEP, job_progress, progress_bar


def test_off_a_terminal_it_writes_a_plain_line_per_step_and_stage_change():
    stream = io.StringIO()
    update = progress_bar("train", stream)                 # a StringIO is not a terminal
    for k in range(101):                                   # 0.00, 0.01, ..., 1.00
        update(k / 100, "fit" if k < 50 else "store")
    update(1.0, "done")                                    # after the end: nothing more
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    # 0, 10, ..., 40 % fit; the stage change at 50 %; 60 ... 100 % store
    assert lines == [f"train: {p:3d}% fit" for p in (0, 10, 20, 30, 40)] + [
        f"train: {p:3d}% store" for p in (50, 60, 70, 80, 90, 100)]
    assert LINE_STEP == 0.1


def test_progress_is_clamped_and_a_final_line_is_written_once():
    stream = io.StringIO()
    update = progress_bar("x", stream, terminal=False)
    update(-0.5, "a")
    update(0.05, "a")                                      # under one step: no line
    update(1.7, "a")
    update(0.2, "a")                                       # after the end: nothing
    assert stream.getvalue().splitlines() == ["x:   0% a", "x: 100% a"]


def test_on_a_terminal_it_is_a_bar_redrawn_in_place():
    stream = io.StringIO()
    update = progress_bar("train", stream, terminal=True)
    update(0.25, "fit")
    update(1.0, "done")
    text = stream.getvalue()
    assert "\r" in text and "25%" in text and "100%" in text and "done" in text


def test_job_progress_draws_a_jobs_states():
    stream = io.StringIO()
    report = job_progress("job_1", stream, terminal=False)
    report(SimpleNamespace(progress=0.0, stage="", status="queued"))
    report(SimpleNamespace(progress=1.0, stage="stored", status="succeeded"))
    assert stream.getvalue().splitlines() == ["job_1:   0% queued", "job_1: 100% stored"]
