"""What the command line prints: messages verbatim (no Rich markup), help readable at 80 columns, whole lines
when the output is not a terminal, a demo folder pointed to its run/."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bad_inputs_table as table

ROOT = Path(__file__).resolve().parent.parent
VERBS = ("calibrate", "run", "report", "view", "export", "pick", "explore", "associate", "track", "demo")


def _rigsfm(args, cwd, **env) -> subprocess.CompletedProcess:
    """``rigsfm ARGS`` as a user runs it, its output piped (not a terminal)."""
    return subprocess.run([sys.executable, "-m", "rigsfm", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(ROOT), **env}, timeout=300)


def _case(did: str) -> table.Case:
    return next(case for case in table.CASES if case.did == did)


@pytest.mark.parametrize("did, shown", [
    ("an image folder named with brackets (`img[/]x`) that does not exist", "image folder 'img[/]x' does not exist"),
    ("a narrow image named with brackets (`frame[cam].png`) without its wide image",
     "'images/rig02/narrow/frame[cam].png' has no wide image"),
    ('a distance in scale.yaml that is not a number (`meters: "[/]"`)', "'meters' must be a number, got '[/]'"),
    ("`--device cuda` with pycolmap's CPU build", "pip install 'rigsfm[gpu]'"),
])
def test_messages_are_printed_verbatim(tmp_path, did, shown):
    """Brackets in names and advice are text: Rich markup ate ``[cam]`` and ``[gpu]`` and raised MarkupError on
    ``[/]`` (a traceback instead of the message)."""
    code, message = table.run_case(_case(did), tmp_path / "case")
    if "cuda" in did and "built without CUDA" not in message:
        pytest.skip("pycolmap here is the CUDA build")
    assert code == 1 and message.startswith("error: ") and shown in message, message


def test_a_demo_folder_points_to_its_run(tmp_path):
    code, message = table.run_case(_case("`rigsfm export` given a demo's folder instead of its run/"), tmp_path / "c")
    assert code == 1
    assert message == "error: 'demo' is a `rigsfm demo` folder, whose result is in its run/ folder: use demo/run (e.g. " \
                      "`rigsfm view demo/run`)"
    assert not (tmp_path / "c" / "demo" / "export").exists()


def test_a_file_given_for_out_is_named_a_file(tmp_path):
    """A file of the run given for OUT was said not to exist (it does: it is not a folder)."""
    code, message = table.run_case(
        _case("`rigsfm export` given a file of the run (`out/narrow_poses.json`) instead of its folder"), tmp_path / "c")
    assert code == 1
    assert message == "error: 'out/narrow_poses.json' is a file, not the folder of a `rigsfm run` (its --out); give " \
                      "that folder"
    assert not (tmp_path / "c" / "out" / "export").exists()


def test_an_unfinished_run_is_named_by_export_images(tmp_path):
    """A run stopped before its summary.json (Ctrl-C in the self-check): `export --images` blamed a summary.json that
    does not exist for naming no image folder."""
    code, message = table.run_case(
        _case("`export --format wildtrack --images` of a run stopped before its summary.json"), tmp_path / "c")
    assert code == 1
    assert message == "error: out/summary.json is missing (the run stopped before writing it), so the run's image " \
                      "folder is unknown: re-run the same `rigsfm run` command to finish it, or export without --images"
    assert not (tmp_path / "c" / "out" / "export").exists()


def test_track_given_the_workspace_for_new_images_says_so(tmp_path):
    """`rigsfm track OUT OUT` read the reference, then called OUT's export, mapping, sparse and track folders rigs
    that are not in the model."""
    code, message = table.run_case(_case("`rigsfm track OUT OUT` (the workspace given for the new images)"),
                                   tmp_path / "c")
    assert code == 1
    assert message == "error: NEW_IMAGES 'out' is the workspace OUT, whose folders are not rigs: give the folder of " \
                      "the new recording (<rig>/<wide|narrow>/<frame file>)"
    assert not (tmp_path / "c" / "out" / "track").exists()


def test_the_image_folder_given_for_out_is_named(tmp_path):
    """IMAGES given where OUT was meant: the error said to `rigsfm run ... --out images`, which writes a run into the
    image folder (refused by `run`: its folders must be rigs)."""
    code, message = table.run_case(_case("`rigsfm report` given the image folder instead of OUT"), tmp_path / "c")
    assert code == 1
    assert message == "error: 'images' is an image folder (<rig>/wide/...), not the --out folder of a `rigsfm run`: " \
                      "give that folder (`rigsfm run images --rigs rigs.yaml --out OUT` makes one)"
    code, message = table.run_case(_case("`rigsfm report` on a folder without a result"), tmp_path / "d")
    assert code == 1 and message == "error: 'notes' holds no result ('notes/sparse' is missing): run `rigsfm run ... " \
                                    "--out notes` first"


def _options(help_text: str) -> list[tuple[str, str]]:
    """(names and metavar, description) of each option in click's help."""
    block = help_text.split("\nOptions:\n", 1)[1]
    options: list[list[str]] = []
    for line in block.splitlines():
        if re.match(r"^  -", line):
            name, _, rest = line.strip().partition("  ")
            options.append([name, rest.strip()])
        elif line.strip() and options:
            options[-1][1] += " " + line.strip()
    return [(name, text) for name, text in options]


@pytest.mark.parametrize("verb", VERBS)
def test_help_at_80_columns(tmp_path, verb):
    done = _rigsfm([verb, "--help"], tmp_path, COLUMNS="80")
    assert done.returncode == 0, done.stderr
    text = done.stdout
    assert "…" not in text and "<bool>" not in text and " range>" not in text
    assert max(len(line) for line in text.splitlines()) <= 80
    usage = text.splitlines()[0]
    assert usage.startswith(f"Usage: rigsfm {verb} [OPTIONS]") and "{" not in usage, usage
    options = _options(text)
    assert options
    for name, description in options:
        flag = " " not in name.split(", ")[-1] and "/" not in name  # --overwrite: no value, off unless given
        if name.startswith("-h") or flag or "[required]" in description:
            continue
        assert "[default: " in description, (verb, name, description)
    assert len(text.splitlines()) < 100  # descriptions wrapped at ~45 columns, not ~15


def test_piped_output_keeps_whole_lines(tmp_path):
    """Output that is not a terminal is not wrapped at an assumed 80 columns."""
    table.workspace(tmp_path)
    dest = tmp_path / ("an export folder with a name long enough to pass eighty columns on its own " + "x" * 20)
    done = _rigsfm(["export", "out", "--format", "json", "--dest", dest], tmp_path, COLUMNS="")
    assert done.returncode == 0, done.stderr
    assert f"exported json: {dest}" in done.stdout.splitlines(), done.stdout


@pytest.mark.parametrize("args", [
    ["run", "missing", "--rigs", "rigs.yaml", "--out", "out"],
    ["associate", "missing", "detections.csv"],
    ["track", "missing", "new"],
])
def test_an_immediate_error_prints_no_progress_display(tmp_path, args):
    """An error before any work is the command's only output: no empty bar (or blank line, piped) above it."""
    done = _rigsfm(args, tmp_path)
    assert done.returncode == 1, done.stderr
    assert done.stdout == "", done.stdout
    assert done.stderr.startswith("error: "), done.stderr


def test_stage_bars_count_time_from_the_stage_start(tmp_path):
    """Feature extraction and matching report their count only as they finish on small inputs: each stage
    announces its start (stage, 0, 0), and the bar's clock runs from there."""
    from rich.progress import Progress

    from rigsfm.cli.common import StageProgress, progress_bars
    from rigsfm.core.errors import ReconstructionError
    from rigsfm.run.pipeline import run

    table.inputs(tmp_path)
    calls = []
    with pytest.raises(ReconstructionError):  # two 64x48 noise images: no model, after features and matching
        run(tmp_path / "images", tmp_path / "rigs.yaml", tmp_path / "out",
            progress=lambda *call: calls.append(call))
    for stage in ("features", "matching", "mapping"):
        first = next(call for call in calls if call[0] == stage)
        assert first[1] == 0, calls
    assert calls[0] == ("features", 0, 0)

    now = [100.0]
    bars = progress_bars()
    progress = Progress(*bars.columns, get_time=lambda: now[0], auto_refresh=False, disable=True)
    report = StageProgress(progress)
    report("features", 0, 0)
    now[0] += 21.0
    report("features", 12, 12)
    task = progress.tasks[0]
    assert (task.completed, task.total) == (12, 12)
    assert progress.columns[-1].render(task).plain == "0:00:21"


@pytest.mark.slow
def test_demo_says_where_its_result_is_and_its_commands_work(tmp_path):
    """The demo's last lines name OUT/run and the exact view and export commands; the export one runs as printed."""
    import shlex

    out = tmp_path / "a demo"  # a space: the printed commands quote it
    done = _rigsfm(["demo", out, "--num-rigs", "4", "--arc-deg", "90", "--image-scale", "0.3"], tmp_path)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    run = shlex.quote(str(out / "run"))
    assert f"result: {out / 'run'} (scene: {out / 'scene'}, accuracy against ground truth: {out / 'accuracy.json'})" \
        in lines
    assert f"  look at it:  rigsfm view {run}   (without a display: rigsfm view {run} --screenshot view.png)" in lines
    export = next(line for line in lines if line.startswith("  export it:   rigsfm export "))
    command = shlex.split(export.split(":", 1)[1].split("   (or")[0])
    assert command[:2] == ["rigsfm", "export"]
    exported = _rigsfm(command[1:], tmp_path)
    assert exported.returncode == 0, exported.stderr
    assert (out / "run" / "export" / "json").is_dir()
    # The demo's folder itself, given to view/export/report, names its run/.
    refused = _rigsfm(["report", out], tmp_path)
    assert refused.returncode == 1 and f"use {out / 'run'}" in refused.stderr, refused.stderr


def test_log_lines_follow_a_replaced_stderr(monkeypatch):
    """An in-process command configures logging on the stderr of its call; a later record, after that stream was
    closed and replaced (pytest does so between tests), goes to the new stream instead of raising inside logging."""
    import io
    import logging

    from rigsfm.cli.common import configure_logging

    first, second = io.StringIO(), io.StringIO()
    monkeypatch.setattr(sys, "stderr", first)
    configure_logging(False)
    try:
        logging.getLogger("rigsfm.test").warning("to the first stream")
        first.close()
        monkeypatch.setattr(sys, "stderr", second)
        logging.getLogger("rigsfm.test").warning("to the second stream")
    finally:
        logging.basicConfig(level=logging.WARNING, handlers=[logging.NullHandler()], force=True)
    assert "to the second stream" in second.getvalue()
    assert "Logging error" not in second.getvalue()


def test_terminal_log_lines_show_the_level_once(monkeypatch):
    """On a terminal a warning reads 'WARNING  text', not 'WARNING  WARNING:rigsfm.module:text' (logging's
    BASIC_FORMAT, which basicConfig gives a handler that has no formatter)."""
    import io
    import logging

    from rich.console import Console

    import rigsfm.cli.common as common

    terminal = Console(file=io.StringIO(), force_terminal=True, width=200, color_system=None)
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    monkeypatch.setattr(common, "err_console", terminal)
    common.configure_logging(False)
    try:
        logging.getLogger("rigsfm.test").warning("frame0000.png: a warning")
    finally:
        logging.basicConfig(level=logging.WARNING, handlers=[logging.NullHandler()], force=True)
    text = terminal.file.getvalue()
    assert "frame0000.png: a warning" in text, text
    assert text.count("WARNING") == 1 and "rigsfm.test" not in text, text


def test_an_os_error_names_the_real_file_not_the_temporary_one(tmp_path, capsys):
    """An atomic write fails on its temporary file or inside a temporary folder (a full disk while export writes
    DEST's files): the line names the file the user asked for."""
    import errno

    import typer

    from rigsfm.cli.common import fail_cleanly
    from rigsfm.core.io import real_path

    assert real_path("out/.export.k2j_x9aq.tmp/poses.json") == "out/export/poses.json"
    assert real_path("/d/.summary.json.abcd1234.tmp") == "/d/summary.json"
    assert real_path("/d/.hidden/plain.tmp") == "/d/.hidden/plain.tmp"  # not a name rigsfm made

    @fail_cleanly
    def export() -> None:
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / ".dest.q1w2e3r4.tmp" / "poses.json"))

    with pytest.raises(typer.Exit):
        export()
    said = capsys.readouterr().err
    assert f"{tmp_path / 'dest' / 'poses.json'}: the disk is full" in said and ".tmp" not in said, said


def test_a_refused_run_does_not_say_it_lowered_the_mappers_thresholds(tmp_path):
    """Manual matches into an OUT holding a result: its red line, without the warning that the mapper's thresholds
    are lowered for them (said first, for a mapper that never ran). rigs.yaml's own warnings may precede it."""
    (table.workspace(tmp_path) / "summary.json").write_text("{}")  # finished
    rows = [f"rig01/wide/f0.png,{5 + 6 * k},{4 + 4 * (k % 3) + k},rig02/wide/f0.png,{8 + 5 * k},{6 + 3 * (k % 4) + k}"
            for k in range(9)]
    (tmp_path / "m.csv").write_text("image_a,x_a,y_a,image_b,x_b,y_b\n" + "\n".join(rows) + "\n")
    done = _rigsfm(["run", "images", "--rigs", "rigs.yaml", "--out", "out", "--manual-matches", "m.csv"], tmp_path)
    lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip()]
    assert done.returncode == 1 and lines[-1].startswith("error: 'out' already holds a result"), lines
    assert not [line for line in lines if "Manual matches given" in line], lines
