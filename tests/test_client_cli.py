"""The ``facesynth`` client subcommands (service.client_cli) against the real app on a
loopback port: every command once, its output and its exit code.

The tiny sheet actor of the API tests is uploaded from files (NPZ neutral, JSON layout, NPZ
clips), a PDM is trained as a job and run on a CSV marker take, a shape-space model on an
NPZ of frames; jobs are listed, watched and cancelled; refusals and an unreachable server
give the documented exit codes.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from service.cli import main
from service.client_cli import EXIT_JOB_FAILED, EXIT_OK, EXIT_REJECTED, EXIT_SERVER
from service.io.exr import read_map
from service.io.markers import MarkerSequence, write_markers_csv
from service.io.mesh import read_obj
from tests.api.conftest import (SHEET_MARKERS, SHEET_PARAMS, layout_body, npz, sheet, sheet_clips,
                                sheet_motion)
from tests.servers import serve_app

PDM_PARAMS = {"medium_resolution": 32, "fine_resolution": 32}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    running = serve_app(tmp_path_factory.mktemp("cli-server"), worker=True)
    yield running
    running.stop()


def run(capsys, server, *argv: str) -> tuple[int, str, str]:
    """``facesynth ARGV --server URL``: (exit code, stdout, stderr)."""
    code = main([*argv, "--server", server.url])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """The sheet actor's uploads as files, and a CSV take of its markers."""
    d = tmp_path_factory.mktemp("cli-files")
    V, F, uv = sheet(16, 13)
    (d / "neutral.npz").write_bytes(npz(vertices=V, faces=F, uv=uv))
    (d / "markers.json").write_bytes(layout_body(SHEET_MARKERS))
    for name, body in sheet_clips(V).items():
        (d / f"{name}.npz").write_bytes(body)
    take = sheet_motion(V, 5, 0.15)
    write_markers_csv(d / "take.csv", MarkerSequence(take[:, list(SHEET_MARKERS)],
                                                     tuple(f"M{k}" for k in range(len(SHEET_MARKERS))), 30.0))
    (d / "frames.npz").write_bytes(npz(vertices=take, fps=np.float64(30.0)))
    return d


def test_the_story_through_the_cli(capsys, server, files, tmp_path):
    code, out, _ = run(capsys, server, "actors", "create", "sheet", "--metadata", '{"take": 1}')
    assert code == EXIT_OK
    actor = out.strip()
    code, out, _ = run(capsys, server, "actors", "list", "--json")
    assert code == EXIT_OK and [a["id"] for a in json.loads(out)] == [actor]

    assert run(capsys, server, "upload", "neutral", actor, str(files / "neutral.npz"))[0] == EXIT_OK
    code, out, _ = run(capsys, server, "upload", "markers", actor, str(files / "markers.json"))
    assert code == EXIT_OK and json.loads(out)["marker_count"] == 4
    clips = []
    for name in ("rise", "fall"):
        code, out, _ = run(capsys, server, "upload", "clip", actor, str(files / f"{name}.npz"), "--name", name)
        assert code == EXIT_OK
        clips.append(out.strip())

    code, out, err = run(capsys, server, "train", actor, "--kind", "pdm", "--clips", *clips,
                         "--params", json.dumps(PDM_PARAMS), "--set", "order=linear")
    assert code == EXIT_OK, err
    pdm = out.strip()
    assert "succeeded" in err
    code, out, _ = run(capsys, server, "models", "list", actor)
    assert code == EXIT_OK and pdm in out and "ready" in out

    # a marker take → per-frame OBJ and EXR
    code, out, err = run(capsys, server, "synthesize", pdm, str(files / "take.csv"), "-o", str(tmp_path / "obj"))
    assert code == EXIT_OK, err
    objs = sorted((tmp_path / "obj").glob("frame_*.obj"))
    assert len(objs) == 5 and read_obj(objs[0]).vertices.shape == (16 * 13, 3)
    assert read_map(sorted((tmp_path / "obj").glob("frame_*_displacement.exr"))[0]).shape == (32, 32)
    # … or one NPZ
    code, out, _ = run(capsys, server, "synthesize", pdm, str(files / "take.csv"), "-o", str(tmp_path / "npz"),
                       "--format", "npz")
    assert code == EXIT_OK
    with np.load(tmp_path / "npz" / "take.npz") as result:
        assert result["vertices"].shape == (5, 16 * 13, 3)

    code, out, err = run(capsys, server, "train", actor, "--kind", "shape_space", "--clips", *clips,
                         "--params", json.dumps(SHEET_PARAMS))
    assert code == EXIT_OK, err
    shape = out.strip()
    code, out, err = run(capsys, server, "enhance", shape, str(files / "frames.npz"), "-o", str(tmp_path / "enh"),
                         "--format", "npz")
    assert code == EXIT_OK, err
    with np.load(tmp_path / "enh" / "frames.npz") as result:
        assert result["vertices"].shape == (5, 16 * 13, 3)

    code, out, _ = run(capsys, server, "models", "export", pdm, "-o", str(tmp_path / "export"))
    assert code == EXIT_OK
    assert json.loads((tmp_path / "export" / "model.json").read_text())["id"] == pdm
    assert len(list((tmp_path / "export").glob("*.exr"))) >= 1

    code, out, _ = run(capsys, server, "jobs", "list", "--actor", actor)
    assert code == EXIT_OK and out.count("succeeded") == 5          # 2 trainings, 3 syntheses
    code, _, err = run(capsys, server, "jobs", "watch", json.loads(
        run(capsys, server, "jobs", "list", "--actor", actor, "--json")[1])[0]["id"])
    assert code == EXIT_OK and "succeeded" in err

    # deleting an actor with models needs --cascade: a refusal is exit code 3
    code, _, err = run(capsys, server, "actors", "delete", actor)
    assert code == EXIT_REJECTED and "409" in err
    assert run(capsys, server, "actors", "delete", actor, "--cascade")[0] == EXIT_OK


def test_a_cancelled_job_and_refusals_have_their_exit_codes(capsys, server, files):
    actor = run(capsys, server, "actors", "create", "other")[1].strip()
    run(capsys, server, "upload", "neutral", actor, str(files / "neutral.npz"))
    run(capsys, server, "upload", "markers", actor, str(files / "markers.json"))
    clip = run(capsys, server, "upload", "clip", actor, str(files / "rise.npz"))[1].strip()
    code, out, _ = run(capsys, server, "train", actor, "--kind", "pdm", "--clips", clip,
                       "--params", json.dumps(PDM_PARAMS), "--no-wait")
    assert code == EXIT_OK
    job = out.split()[-1]
    assert job.startswith("job_")
    code, _, err = run(capsys, server, "jobs", "cancel", job)
    assert code == EXIT_OK
    code, _, err = run(capsys, server, "jobs", "watch", job)
    assert code in (EXIT_OK, EXIT_JOB_FAILED)        # it may have finished before the cancel
    if code == EXIT_JOB_FAILED:
        assert "cancelled" in err

    code, _, err = run(capsys, server, "train", actor, "--kind", "nope", "--clips", clip)
    assert code == EXIT_REJECTED and "'nope'" in err and "'pdm'" in err
    code, _, err = run(capsys, server, "jobs", "watch", "job_00000000000000000000000000")
    assert code == EXIT_REJECTED and "404" in err
    with pytest.raises(SystemExit) as exit_info:                          # argparse: usage
        main(["train", actor])
    assert exit_info.value.code == 2
    assert main(["actors", "list", "--server", "http://127.0.0.1:9"]) == EXIT_SERVER
    assert "error:" in capsys.readouterr().err


def test_exit_codes_are_documented():
    import service.client_cli as cli

    for code in (EXIT_OK, EXIT_JOB_FAILED, 2, EXIT_REJECTED, EXIT_SERVER):
        assert f"    {code}  " in cli.__doc__


def _parsers(parser):
    """The parser and every subcommand's parser, recursively."""
    import argparse

    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_every_positional_argument_has_help_and_no_help_has_rst_markup():
    from service.cli import build_parser

    parsers = list(_parsers(build_parser()))
    assert len(parsers) > 30
    for parser in parsers:
        for action in parser._actions:
            if not action.option_strings and action.nargs != 0 and action.dest != "help" and \
                    action.__class__.__name__ != "_SubParsersAction":
                assert action.help, f"{parser.prog} {action.dest} has no help"
        assert "``" not in parser.format_help(), parser.prog


def test_global_server_and_token_come_before_or_after_the_command():
    from service.cli import build_parser

    parser = build_parser()
    before = parser.parse_args(["--server", "http://a:1", "--token", "t", "jobs", "list"])
    after = parser.parse_args(["jobs", "list", "--server", "http://b:2"])
    neither = parser.parse_args(["jobs", "list"])
    assert (before.server, before.token) == ("http://a:1", "t")
    assert (after.server, after.token) == ("http://b:2", None)
    assert (neither.server, neither.token) == (None, None)
    both = parser.parse_args(["--server", "http://a:1", "jobs", "list", "--server", "http://b:2"])
    assert both.server == "http://b:2"                      # the nearer one wins


def test_synthesize_marker_filter_smooths_the_take_on_the_server(capsys, server, files, tmp_path):
    """``--marker-filter 3`` = the job's ``marker_filter_frames`` 3: the same result as
    synthesizing the take filtered locally by the server's filter, and not the raw take's."""
    from service.geometry.marker_filter import filter_performance

    actor = run(capsys, server, "actors", "create", "filtered")[1].strip()
    run(capsys, server, "upload", "neutral", actor, str(files / "neutral.npz"))
    run(capsys, server, "upload", "markers", actor, str(files / "markers.json"))
    clips = [run(capsys, server, "upload", "clip", actor, str(files / f"{n}.npz"))[1].strip()
             for n in ("rise", "fall")]
    code, out, err = run(capsys, server, "train", actor, "--kind", "pdm", "--clips", *clips,
                         "--params", json.dumps(PDM_PARAMS), "--set", "order=linear")
    assert code == EXIT_OK, err
    pdm = out.strip()
    V, _, _ = sheet(16, 13)
    take = sheet_motion(V, 9, 0.1)[:, list(SHEET_MARKERS)]
    take += np.random.default_rng(3).normal(scale=0.3, size=take.shape)       # mocap noise, mm
    (tmp_path / "raw.npz").write_bytes(npz(markers=take, fps=np.float64(30.0)))
    (tmp_path / "pre.npz").write_bytes(npz(markers=filter_performance(take, 3.0), fps=np.float64(30.0)))

    def result(name, *extra):
        code, _, err = run(capsys, server, "synthesize", pdm, str(tmp_path / f"{name}.npz"),
                           "-o", str(tmp_path / f"out-{name}-{len(extra)}"), "--format", "npz", *extra)
        assert code == EXIT_OK, err
        with np.load(tmp_path / f"out-{name}-{len(extra)}" / f"{name}.npz") as r:
            return r["vertices"].astype(np.float64)

    filtered, raw, pre = result("raw", "--marker-filter", "3"), result("raw"), result("pre")
    # float32 uploads and outputs: the pre-filtered take is rounded to float32 before the
    # shell solve, the server filters the raw take in float64 (measured 1.3e-4 mm)
    assert np.abs(filtered - pre).max() < 1e-3
    assert np.abs(filtered - raw).max() > 0.05                               # the filter acted
    # a bad σ is a usage error (exit 2) before anything is sent; one above the server's
    # limit is the server's 422 (exit 3)
    with pytest.raises(SystemExit) as exit_info:
        main(["synthesize", pdm, str(tmp_path / "raw.npz"), "-o", str(tmp_path / "x"),
              "--marker-filter", "-1", "--server", server.url])
    assert exit_info.value.code == 2 and "frames >= 0" in capsys.readouterr().err
    code, _, err = run(capsys, server, "synthesize", pdm, str(tmp_path / "raw.npz"), "-o",
                       str(tmp_path / "y"), "--marker-filter", "1000")
    assert code == EXIT_REJECTED and "marker_filter_frames" in err and not (tmp_path / "y").exists()
    assert run(capsys, server, "actors", "delete", actor, "--cascade")[0] == EXIT_OK


def test_marker_filter_argument_takes_frames_or_auto():
    from service.client_cli import _filter_frames

    assert _filter_frames("3") == 3.0 and _filter_frames("auto") == "auto"
    for bad in ("-1", "inf", "smooth"):
        with pytest.raises(argparse.ArgumentTypeError, match="'auto'"):
            _filter_frames(bad)
