"""Faults a new user runs into, on one rendered 3-rig scene run once: names with spaces, exports next to other
files, two commands on one OUT, a full / read-only / forbidden disk, --strict, damaged workspace files, a Ray
address nothing listens on, new recordings reusing old file names, a picker save that empties the CSV."""

import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import yaml
from conftest import copy_run
from support import picker_images
from typer.testing import CliRunner

from rigsfm.cli import app
from rigsfm.core.errors import InputError
from rigsfm.core.workspace import Workspace
from rigsfm.inspect.export import MANIFEST
from rigsfm.run.pipeline import RunResult
from rigsfm.synth.demo import score
from rigsfm.synth.scene import SceneOptions

pytestmark = pytest.mark.slow  # end-to-end runs on rendered images (`-m 'not slow'` skips them)

REPO = Path(__file__).resolve().parents[1]


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def one_error_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    return errors[0]


@pytest.fixture(scope="module")
def scene(three_rig_run, tmp_path_factory):
    dataset, shared, _ = three_rig_run  # the session's run (conftest), copied: faults are made in OUT
    return dataset, copy_run(shared, tmp_path_factory.mktemp("faults") / "out")


def copy_workspace(out: Path, where: Path) -> Path:
    copy = where / "out"
    shutil.copytree(out, copy)
    return copy


# --- names with spaces -------------------------------------------------------------------------------------------

def test_rig_and_frame_names_with_spaces_register_and_are_accurate(scene, tmp_path):
    """COLMAP's pairs file is split at spaces: such pairs are matched directly (features.match_pairs_directly)."""
    dataset, _ = scene
    images = tmp_path / "images"
    shutil.copytree(dataset.images, images)
    (images / "rig02").rename(images / "rig 02")
    for sensor in ("wide", "narrow"):
        (images / "rig 02" / sensor / "frame0000.png").rename(images / "rig 02" / sensor / "frame 0000.png")
    rigs = yaml.safe_load(dataset.rigs.read_text())
    rigs["rigs"][1]["name"] = "rig 02"
    (tmp_path / "rigs.yaml").write_text(yaml.safe_dump(rigs))
    scale_text = dataset.scale.read_text().replace("rig02/wide/frame0000.png", "rig 02/wide/frame 0000.png")
    assert "rig 02" in scale_text
    (tmp_path / "scale.yaml").write_text(scale_text)
    out = tmp_path / "out"
    result = invoke("run", images, "--rigs", tmp_path / "rigs.yaml", "--scale", tmp_path / "scale.yaml", "--out", out)
    assert result.exit_code == 0, result.output
    assert "registered: wide 3/3, narrow 3/3" in result.output
    summary = json.loads((out / "summary.json").read_text())
    assert [m["label"] for m in summary["scale"]["measurements"]] == ["rig01/wide - rig03/wide", "known_length[0]"]
    reconstruction = pycolmap.Reconstruction(out / "sparse")
    for image in reconstruction.images.values():
        image.name = image.name.replace("rig 02", "rig02").replace("frame 0000", "frame0000")
    accuracy = score(RunResult(None, reconstruction, {}), dataset)
    assert accuracy["narrow"]["registered"] == 3
    assert accuracy["narrow"]["relative_rotation_deg"]["max"] < 0.3
    assert accuracy["narrow"]["distance_error_percent"]["max"] < 0.5


# --- export never deletes what rigsfm did not write -----------------------------------------------------------------

def test_export_refuses_the_workspace_and_folders_that_hold_it(scene):
    _, out = scene
    before = sorted(p.name for p in out.iterdir())
    for dest in (out, out.parent, out / "sparse"):
        result = invoke("export", out, "--format", "json", "--dest", dest, "--overwrite")
        assert result.exit_code == 1
        assert f"--dest '{dest}' is" in one_error_line(result)
    assert sorted(p.name for p in out.iterdir()) == before


def test_export_refuses_a_folder_with_other_files_and_touches_nothing(scene, tmp_path):
    _, out = scene
    dest = tmp_path / "thesis"
    dest.mkdir()
    (dest / "chapter1.tex").write_text("precious")
    result = invoke("export", out, "--format", "json", "--dest", dest, "--overwrite")
    assert result.exit_code == 1
    assert "holds files rigsfm did not write (chapter1.tex)" in one_error_line(result)
    assert sorted(p.name for p in dest.iterdir()) == ["chapter1.tex"]
    assert (dest / "chapter1.tex").read_text() == "precious"


def test_export_overwrite_removes_only_the_files_of_its_manifest(scene, tmp_path):
    _, out = scene
    dest = tmp_path / "export"
    assert invoke("export", out, "--format", "json", "--dest", dest).exit_code == 0
    manifest = json.loads((dest / MANIFEST).read_text())
    assert manifest["files"] == ["poses.json"]
    (dest / "stale.json").write_text("{}")  # an earlier export's file, listed in its manifest
    (dest / MANIFEST).write_text(json.dumps({**manifest, "files": ["poses.json", "stale.json"],
                                             "sha256": {**manifest["sha256"],
                                                        "stale.json": hashlib.sha256(b"{}").hexdigest()}}))
    result = invoke("export", out, "--format", "json", "--dest", dest)
    assert result.exit_code == 1 and "pass --overwrite" in one_error_line(result)
    assert invoke("export", out, "--format", "json", "--dest", dest, "--overwrite").exit_code == 0
    assert sorted(p.name for p in dest.iterdir()) == sorted([MANIFEST, "poses.json"])
    (dest / "notes.txt").write_text("mine")  # not in the manifest: the next --overwrite refuses
    result = invoke("export", out, "--format", "json", "--dest", dest, "--overwrite")
    assert result.exit_code == 1 and "notes.txt" in one_error_line(result)
    assert (dest / "notes.txt").read_text() == "mine" and (dest / "poses.json").is_file()


# --- one command at a time on OUT; full, read-only and forbidden disks ----------------------------------------------------

def test_a_second_run_on_one_out_is_refused_with_the_first_ones_pid(scene):
    dataset, out = scene
    with Workspace(out).lock():
        result = invoke("run", dataset.images, "--rigs", dataset.rigs, "--out", out, "--overwrite")
    assert result.exit_code == 1
    assert f"'{out}' is in use by process {os.getpid()} (another rigsfm command)" in one_error_line(result)
    assert (out / "summary.json").is_file()


def test_report_on_an_out_in_use_is_refused_and_writes_nothing(scene, tmp_path):
    """`rigsfm report OUT` while a `rigsfm run --overwrite` held OUT wrote the old result's report.html among the
    run's files, exit 0 (README: one command at a time writes an OUT)."""
    _, out = scene
    copy = copy_workspace(out, tmp_path)
    (copy / "report.html").unlink()
    with Workspace(copy).lock():
        result = invoke("report", copy)
    assert result.exit_code == 1
    assert f"'{copy}' is in use by process {os.getpid()} (another rigsfm command)" in one_error_line(result)
    assert not (copy / "report.html").exists()
    assert invoke("report", copy).exit_code == 0 and (copy / "report.html").is_file()


def _run_isolated(wrapper: list[str], dataset, out: Path, setup: str = "") -> subprocess.CompletedProcess:
    """`rigsfm run` in a child process under ``wrapper`` (unshare, setpriv), after the shell commands ``setup``."""
    command = (f"{setup} {sys.executable} -m rigsfm run {dataset.images} --rigs {dataset.rigs} --scale "
               f"{dataset.scale} --out {out}")
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1", "COLUMNS": "300"}
    return subprocess.run([*wrapper, "sh", "-c", command], capture_output=True, text=True, env=env, timeout=300)


def _isolation_available(wrapper: list[str]) -> bool:
    try:
        return subprocess.run([*wrapper, "true"], capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.mark.parametrize("size", ["8k", "300k", "3m"])  # fails creating the database, in its WAL, while extracting
def test_a_full_disk_is_one_line_naming_out(scene, tmp_path, size):
    if not _isolation_available(["unshare", "-m"]):
        pytest.skip("needs `unshare -m` (mount namespaces) to mount a small tmpfs")
    dataset, _ = scene
    mount = tmp_path / "disk"
    mount.mkdir()
    done = _run_isolated(["unshare", "-m"], dataset, mount / "out", f"mount -t tmpfs -o size={size} tmpfs {mount} &&")
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"error: cannot write in '{mount / 'out'}': the disk is full" in done.stderr, done.stderr
    assert "internal error" not in done.stderr and "Traceback" not in done.stderr


def test_a_read_only_out_is_one_line(scene, tmp_path):
    if not _isolation_available(["unshare", "-m"]):
        pytest.skip("needs `unshare -m` (mount namespaces) to mount a read-only tmpfs")
    dataset, _ = scene
    mount = tmp_path / "disk"
    mount.mkdir()
    done = _run_isolated(["unshare", "-m"], dataset, mount / "out", f"mount -t tmpfs -o ro tmpfs {mount} &&")
    assert done.returncode == 1
    assert f"error: cannot write in '{mount / 'out'}': the file system is read-only; choose a folder you can write to" \
        in done.stderr, done.stderr


def test_a_forbidden_out_is_one_line(scene, tmp_path):
    nobody = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
    if os.geteuid() != 0 or not _isolation_available(nobody):
        pytest.skip("needs root and setpriv to run as an unprivileged user")
    dataset, _ = scene
    public = Path(tempfile.mkdtemp(prefix="rigsfm-forbidden-", dir="/tmp"))  # pytest's folders are private (0700)
    try:
        public.chmod(0o755)
        copy = render_copy(dataset, public / "scene")
        forbidden = public / "forbidden"
        forbidden.mkdir(mode=0o755)
        done = _run_isolated(nobody, copy, forbidden / "out")
        assert done.returncode == 1
        assert f"error: cannot write in '{forbidden / 'out'}': permission denied; choose a folder you can write to" \
            in done.stderr, done.stderr
        (copy.rigs).chmod(0o600)
        done = _run_isolated(nobody, copy, public / "out")  # typer's own check of the path: a usage error
        assert done.returncode == 2 and "'--rigs': path" in done.stderr and "is not readable" in done.stderr
    finally:
        shutil.rmtree(public)


def render_copy(dataset, where: Path):
    """The dataset's images, rigs.yaml and scale.yaml under ``where``, readable by everyone."""
    shutil.copytree(dataset.images, where / "images")
    for name in ("rigs.yaml", "scale.yaml"):
        shutil.copy(dataset.root / name, where / name)
    for path in [where, *where.rglob("*")]:
        path.chmod(0o755 if path.is_dir() else 0o644)
    return type(dataset)(where, where / "images", where / "rigs.yaml", where / "rigs.yaml", where / "scale.yaml",
                         where / "ground_truth", dataset.options, dataset.image_names)


# --- --strict, damaged files --------------------------------------------------------------------------------------------

def test_strict_turns_warnings_into_exit_code_4(scene, tmp_path):
    dataset, out = scene
    copy = copy_workspace(out, tmp_path)
    result = invoke("run", dataset.images, "--rigs", dataset.rigs, "--out", copy, "--overwrite", "--strict")
    assert result.exit_code == 4, result.output
    assert "warning: NOT METRIC" in result.output and "--strict: exit code 4" in result.output
    assert invoke("run", dataset.images, "--rigs", dataset.rigs, "--scale", dataset.scale, "--out", copy,
                  "--overwrite", "--strict").exit_code == 0


MODEL_READERS = ("report", "export", "view", "track")


@pytest.mark.parametrize("damage,words,readers", [
    (lambda out: (out / "sparse" / "images.bin").write_bytes((out / "sparse" / "images.bin").read_bytes()[:100]),
     r"sparse/images.bin' is truncated or damaged \(100 B; ",
     MODEL_READERS),
    (lambda out: (out / "sparse" / "images.bin").write_bytes((out / "sparse" / "images.bin").read_bytes()[:300]),
     r"sparse/images.bin' is truncated or damaged \(300 B; ",
     ("report",)),
    (lambda out: (out / "sparse" / "points3D.bin").write_bytes(b""),
     r"holds no complete COLMAP model \(points3D.bin empty\)", MODEL_READERS),
    (lambda out: (out / "narrow_poses.json").write_text('{"metric": true, "narrow": ['),
     r"narrow_poses.json' is not valid JSON \(.*\): re-run `rigsfm run IMAGES --rigs rigs.yaml --out .* --overwrite`",
     ("report",)),
    (lambda out: (out / "summary.json").write_text("[1, 2]"), r"summary.json is not a valid summary", ("report", "export")),
    (lambda out: (out / "track").mkdir() or (out / "track" / "poses.json").write_text("{"),
     r"track/poses.json' is not valid JSON .*: re-run `rigsfm track OUT NEW_IMAGES --overwrite`", ("report",)),
])
def test_damaged_workspace_files_are_named_by_every_reader(scene, tmp_path, damage, words, readers):
    import re

    dataset, out = scene
    copy = copy_workspace(out, tmp_path)
    damage(copy)
    commands = {"report": ["report", copy], "export": ["export", copy, "--format", "json"],
                "view": ["view", copy, "--screenshot", tmp_path / "v.png"],
                "track": ["track", copy, dataset.images, "--workers", "1"]}
    for reader in readers:
        result = invoke(*commands[reader])
        assert result.exit_code == 1, (reader, result.output)
        assert re.search(words, one_error_line(result)), (reader, result.output)


# --- track: a Ray address nothing listens on; new recordings reusing file names ------------------------------------------

def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ray_address_nobody_listens_on_is_refused_at_once(scene, tmp_path):
    dataset, out = scene
    port = free_port()
    result = invoke("track", out, dataset.images, "--executor", "ray", "--address", f"127.0.0.1:{port}")
    assert result.exit_code == 1
    assert (f"cannot reach the Ray cluster at 127.0.0.1:{port} (connection refused: nothing listens on that port)"
            in one_error_line(result))
    from rigsfm.core.executors import check_reachable

    with pytest.raises(InputError, match=r"--address 'head': expected HOST:PORT, ray://HOST:PORT or auto"):
        check_reachable("head")


def test_a_reused_frame_name_with_new_content_is_refused_until_overwrite(scene, tmp_path):
    """A second recording (or another scene's images) under tracked frame names would replace the earlier results,
    which nothing else keeps: refused, naming the frame and the fix; --overwrite starts the series anew."""
    from rigsfm.core.errors import WorkspaceError
    from rigsfm.track import TrackOptions, track

    dataset, out = scene
    copy = copy_workspace(out, tmp_path)
    new = tmp_path / "new"
    for rig in ("rig01", "rig02"):
        (new / rig / "wide").mkdir(parents=True)
        shutil.copy(dataset.images / rig / "wide" / "frame0000.png", new / rig / "wide" / "frame0000.png")
    options = TrackOptions(workers=1)
    first = track(copy, new, options)
    assert (first.processed, first.skipped) == (2, 0)
    entry = first.poses["rigs"]["rig02"]["frames"][0]
    path = new / "rig02" / "wide" / "frame0000.png"
    assert entry["files"]["wide"]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert entry["files"]["wide"]["size"] == path.stat().st_size
    assert entry["wide"]["rotation_change_deg"] < 0.02

    unchanged = track(copy, new, options)
    assert (unchanged.processed, unchanged.skipped) == (0, 2)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.roll(image, 12, axis=1))  # the camera turned by ~12 px: a new recording, same name
    saved = {p.name: p.read_bytes() for p in (copy / "track").iterdir() if p.is_file()}
    result = invoke_wide("track", copy, new, "--workers", "1")
    assert result.exit_code == 1, result.output
    assert one_error_line(result).startswith(
        f"error: '{copy / 'track' / 'poses.json'}' holds results of 1 frame(s) of the same name tracked from other "
        "images ('rig02/frame0000.png'; a new recording that reuses their file names?): name the new frames so that "
        "they differ from the tracked ones")
    assert "pass --overwrite to start the series anew" in result.output
    assert {p.name: p.read_bytes() for p in (copy / "track").iterdir() if p.is_file()} == saved  # nothing replaced
    with pytest.raises(WorkspaceError, match="rig02/frame0000.png"):
        track(copy, new, options)

    again = track(copy, new, TrackOptions(workers=1, overwrite=True))
    assert (again.processed, again.skipped) == (2, 0)
    moved = again.poses["rigs"]["rig02"]["frames"][0]
    assert moved["files"]["wide"]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert moved["wide"]["rotation_change_deg"] > 0.2  # the new content's pose, not the old one's
    kept = again.poses["rigs"]["rig01"]["frames"][0]
    assert kept["wide"]["rotation_change_deg"] < 0.02
    assert len(json.loads((copy / "track" / "poses.json").read_text())["rigs"]["rig02"]["frames"]) == 1

    (new / "rig01" / "narrow").mkdir()  # the same recording's narrow image, added since: no other images, tracked again
    shutil.copy(dataset.images / "rig01" / "narrow" / "frame0000.png", new / "rig01" / "narrow" / "frame0000.png")
    grown = track(copy, new, options)
    assert (grown.processed, grown.skipped) == (1, 1)
    assert sorted(grown.poses["rigs"]["rig01"]["frames"][0]["files"]) == ["narrow", "wide"]


# --- run: a new recording copied over the old file names; database.db removed under a run ---------------------------

MOVED = SceneOptions(num_rigs=3, arc_deg=120.0, image_scale=0.5, seed=1, radius=17.0, wide_pitch_deg=15.0)


def invoke_wide(*args):
    """``invoke`` with lines as wide as the longest (rich breaks a long path where the terminal's width ends)."""
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "400"})


def test_a_new_recording_under_the_same_names_is_run_on_its_own_content(scene, rendered, tmp_path):
    """The rigs moved (1 m further out, 3 deg more pitch), the new recording is copied over the images of the
    last run, rigs.yaml unchanged: the re-run makes the changed images' features and matches again, says so, and
    delivers the new recording's poses (the old features' are degrees off the new truth)."""
    dataset, out = scene
    moved = rendered(MOVED)
    assert moved.rigs.read_text() == dataset.rigs.read_text()
    copy = copy_workspace(out, tmp_path)
    images = tmp_path / "images"
    shutil.copytree(dataset.images, images)
    args = ["run", images, "--rigs", dataset.rigs, "--scale", moved.scale, "--out", copy, "--overwrite"]
    shutil.copytree(moved.images, images, dirs_exist_ok=True)
    result = invoke_wide(*args)
    assert result.exit_code == 0, result.output
    assert ("3 images changed since the last run in this workspace (rig01/wide/frame0000.png, "
            "rig02/wide/frame0000.png, rig03/wide/frame0000.png): their features and matches are made again"
            in result.output), result.output
    accuracy = score(RunResult(None, pycolmap.Reconstruction(copy / "sparse"), {}), moved)
    assert accuracy["narrow"]["registered"] == 3
    assert accuracy["narrow"]["relative_rotation_deg"]["max"] < 0.3, accuracy["narrow"]


def test_a_database_removed_during_matching_is_named_then_made_again(scene, tmp_path, monkeypatch):
    """COLMAP opens database.db by its path at every step: removed under a run, the next step makes an empty one
    and the mapper found no matches. The run names the file instead, and the same command then makes it again."""
    import rigsfm.run.pipeline
    from rigsfm.core import processes as stages

    dataset, out = scene
    copy = copy_workspace(out, tmp_path)
    args = ["run", dataset.images, "--rigs", dataset.rigs, "--scale", dataset.scale, "--out", copy, "--overwrite"]
    matched = rigsfm.run.pipeline.match_features

    def match_then_lose_the_database(database, *rest, **options):
        done = matched(database, *rest, **options)
        Path(database).unlink()
        pycolmap.Database.open(database).close()  # what COLMAP's matcher leaves, opening the path again
        return done

    monkeypatch.setattr(rigsfm.run.pipeline, "match_features", match_then_lose_the_database)
    with stages.in_process():  # the stage runs the patched function here
        lost = invoke_wide(*args)
    assert lost.exit_code == 1
    assert one_error_line(lost) == (f"error: {copy / 'database.db'} was removed or replaced while this run wrote it: "
                                    "re-run the same command (the database is made again)")
    monkeypatch.undo()
    again = invoke_wide(*args)
    assert again.exit_code == 0, again.output
    assert (f"'{copy / 'database.db'}' holds no images (removed or replaced while a run wrote it?): it is made again"
            in again.output), again.output
    assert json.loads((copy / "summary.json").read_text())["registered"]["narrow"]["registered"] == 3


def test_an_overwrite_stopped_after_the_new_model_is_written_is_not_taken_for_the_old_result(scene, tmp_path,
                                                                                            monkeypatch):
    """`run --overwrite` over a finished OUT, stopped by Ctrl-C in the self-check (after sparse/ and
    narrow_poses.json are rewritten, before summary.json): the old summary.json stayed beside the new model, so the
    OUT read as finished (report.html, a re-run refused without --overwrite) with the old run's numbers."""
    import rigsfm.run.pipeline
    from rigsfm.core.workspace import Workspace
    from rigsfm.run.options import RunOptions

    dataset, out = scene
    copy = copy_workspace(out, tmp_path)

    def stopped(*_, **__):
        raise KeyboardInterrupt

    monkeypatch.setattr(rigsfm.run.pipeline, "_self_check", stopped)
    assert (copy / "report.html").is_file()
    with pytest.raises(KeyboardInterrupt):
        rigsfm.run.pipeline.run(dataset.images, dataset.rigs, copy, dataset.scale, RunOptions(overwrite=True))
    assert (copy / "narrow_poses.json").is_file() and not (copy / "summary.json").exists()
    # nor the old report.html, which showed the replaced result's numbers beside the new model (a new recording's)
    assert not (copy / "report.html").exists()
    Workspace(copy).prepare(overwrite=False)  # unfinished: the same command without --overwrite finishes it


# --- picker: a save that drops the saved pairs keeps a backup ---------------------------------------------------------

def test_picker_put_that_empties_the_csv_keeps_a_backup(tmp_path):
    import urllib.request

    from rigsfm.pick.server import PickerServer
    from rigsfm.pick.session import PickerSession, picker_image
    from rigsfm.run.matching.manual_matches import read_manual_matches

    paths = picker_images(tmp_path)
    csv = tmp_path / "matches.csv"
    other = "rig03/wide/f0.png,1.000,2.000,rig04/wide/f0.png,3.000,4.000\n"
    session = PickerSession(picker_image(paths[0], None), picker_image(paths[1], None), csv)
    server = PickerServer(session)
    try:
        def put(pairs):
            request = urllib.request.Request(server.url + "api/pairs", data=json.dumps({"pairs": pairs}).encode(),
                                             method="PUT", headers={"Content-Type": "application/json"})
            with urllib.request.urlopen(request) as answer:
                return json.loads(answer.read())

        pairs = [[float(i), 2.0 * i, 3.0 + i, 4.0] for i in range(1, 11)]
        put(pairs)
        csv.write_text(csv.read_text() + other)
        session.reload()
        assert "backup" not in put(pairs[:-1])  # an undo drops one pair: no backup
        assert not session.backups()
        full = csv.read_text()
        answer = put([])
        assert session.backups() == [Path(answer["backup"])] and answer["pairs"] == []
        assert Path(answer["backup"]).read_text() == full
        assert [r.image_a for r in read_manual_matches(csv)] == ["rig03/wide/f0.png"]  # other pairs kept
        assert len(read_manual_matches(answer["backup"])) == 10
    finally:
        server.close()


def test_picker_out_that_is_a_folder_is_refused_at_the_start(tmp_path):
    """--out naming a folder started a picker whose every save failed; it is refused before the page opens."""
    from rigsfm.pick.session import PickerSession, picker_image
    from rigsfm.run.matching.manual_matches import ManualMatchError

    paths = picker_images(tmp_path)
    (tmp_path / "picks").mkdir()
    with pytest.raises(ManualMatchError, match=r"'.*picks' is a folder, not a regular file"):
        PickerSession(picker_image(paths[0], None), picker_image(paths[1], None), tmp_path / "picks")


def test_picker_refuses_an_image_that_is_not_a_wide_one_at_the_start(tmp_path):
    """Without --rigs a narrow image, or one outside IMAGES/<rig>/wide/, was served: every pair clicked on it went
    into a CSV `rigsfm run --manual-matches` refuses (names are <rig>/wide/<file>)."""
    import shutil

    from rigsfm.pick.session import picker_image
    from rigsfm.run.matching.manual_matches import ManualMatchError

    wide = picker_images(tmp_path)[0]
    narrow = tmp_path / "images" / "rig01" / "narrow" / "f0.png"
    narrow.parent.mkdir()
    shutil.copy(wide, narrow)
    loose = shutil.copy(wide, tmp_path / "a.png")
    for path in (narrow, Path(loose)):
        with pytest.raises(ManualMatchError, match=r"must be a wide image, IMAGES/<rig>/wide/<file>"):
            picker_image(path, None)
    assert picker_image(wide, None).name == "rig01/wide/f0.png"
