"""rigsfm deletes only what it wrote and reads damaged binary models safely: export's manifest, the demo's scene
folder, the picker's backups and stale pages, and every COLMAP model file cut short or damaged."""

import hashlib
import json
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from bad_inputs_table import workspace
from support import as_from_a_terminal, picker_images
from typer.testing import CliRunner

from rigsfm.cli import app
from rigsfm.core.summary import Summary
from rigsfm.inspect.export import MANIFEST

REPO = Path(__file__).resolve().parents[1]


def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"COLUMNS": "400"})


def one_error_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in result.output, result.output
    return errors[0]


@pytest.fixture()
def out(tmp_path):
    """A small finished workspace whose model has 3D points (300, each seen by the four images)."""
    out = workspace(tmp_path)
    rec = pycolmap.Reconstruction(out / "sparse")
    rng = np.random.default_rng(0)
    for image in rec.images.values():
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(rng.uniform(0, 40, 2)) for _ in range(300)])
    for k in range(300):
        track = pycolmap.Track()
        for image_id in sorted(rec.images):
            track.add_element(image_id, k)
        rec.add_point3D(rng.normal(size=3) + [0.0, 0.0, 5.0], track, np.array([1, 2, 3], np.uint8))
    rec.write(out / "sparse")
    (out / "summary.json").write_text(json.dumps(Summary().to_json()))  # written last by a run that finished
    return out


# --- binary models: sizes checked before pycolmap allocates ---------------------------------------------------------

def cut(path: Path, size: int) -> None:
    path.write_bytes(path.read_bytes()[:size])


@pytest.mark.parametrize("name,size", [("points3D.bin", 1000), ("points3D.bin", 24000), ("images.bin", 100),
                                       ("images.bin", 20000), ("cameras.bin", 50), ("rigs.bin", 60),
                                       ("frames.bin", 100)])
def test_a_cut_model_file_is_named_by_every_reader(out, tmp_path, name, size):
    cut(out / "sparse" / name, size)
    for args in (["report", out], ["export", out, "--format", "json"],
                 ["view", out, "--screenshot", tmp_path / "v.png"]):
        result = invoke(*args)
        assert result.exit_code == 1, (args, result.output)
        line = one_error_line(result)
        assert f"sparse/{name}' is truncated or damaged ({size} B; " in line, line
        assert line.endswith(f"re-run `rigsfm run IMAGES --rigs rigs.yaml --out {out} --overwrite`"), line


def test_a_huge_count_is_refused_before_anything_is_allocated(out):
    """A count of 10^9 points in an intact file: pycolmap alone reserves and loops until memory runs out (here a
    2 GiB address-space limit, so that the old behaviour fails the test instead of filling the machine)."""
    path = out / "sparse" / "points3D.bin"
    data = bytearray(path.read_bytes())
    data[:8] = struct.pack("<Q", 10**9)
    path.write_bytes(bytes(data))
    code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30)); "
            "from rigsfm.cli import app; app(['report', sys.argv[1]], prog_name='rigsfm')")
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "400"}
    done = subprocess.run([sys.executable, "-c", code, str(out)], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 1, done.stderr
    assert "points3D.bin' is truncated or damaged (24908 B; says 1000000000 3D points but only 24900 B follow)" in \
        done.stderr, done.stderr


def test_a_rig_with_only_its_reference_sensor_passes(tmp_path):
    """A rig whose narrow camera has no image (a rig without narrow images) keeps only its reference sensor; as
    the last rig of rigs.bin it leaves just that sensor's 8 bytes, no pose flag, and the file is intact."""
    from rigsfm.core.model_files import check_model_files

    camera = pycolmap.Camera(model="PINHOLE", width=64, height=48, params=[50.0, 50.0, 32.0, 24.0])
    model = pycolmap.Reconstruction()
    for rig_id in (1, 2):
        camera.camera_id = rig_id
        model.add_camera(camera)
        rig = pycolmap.Rig(rig_id=rig_id)
        rig.add_ref_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, rig_id))
        model.add_rig(rig)
    model.write(tmp_path)
    check_model_files(tmp_path)
    cut(tmp_path / "rigs.bin", (tmp_path / "rigs.bin").stat().st_size - 1)
    with pytest.raises(Exception, match="rig 2 says 1 sensors but the file is shorter"):
        check_model_files(tmp_path)


def test_damaged_references_between_files_are_named(out):
    from rigsfm.core.model_files import ModelFileError, check_model_files

    check_model_files(out / "sparse")  # the intact model passes
    path = out / "sparse" / "points3D.bin"
    data = bytearray(path.read_bytes())
    offset = 8 + 51  # the first point's first track element: image id, then 2D point index
    data[offset + 4:offset + 8] = struct.pack("<I", 5000)
    path.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match=r"3D point 1 is seen by 2D point 5000 of image 1, which images.bin"):
        check_model_files(out / "sparse")


# --- export: the manifest is checked before anything is removed -----------------------------------------------------

def export_json(out, dest, *extra):
    return invoke("export", out, "--format", "json", "--dest", dest, *extra)


def test_a_forged_manifest_deletes_nothing_outside_the_export(out, tmp_path):
    """Entries that leave DEST, absolute paths and the user's own images listed without a checksum are all kept."""
    dest = tmp_path / "dest"
    assert export_json(out, dest).exit_code == 0
    database = out / "database.db"
    database.write_bytes(b"SQLite format 3\0 the user's database")
    outside = tmp_path / "elsewhere.txt"
    outside.write_text("keep me")
    (dest / "IMG_0001.jpg").write_bytes(b"the user's photo")
    manifest = json.loads((dest / MANIFEST).read_text())
    manifest["files"] += ["../out/database.db", str(outside), str(database), "IMG_0001.jpg", "..", "."]
    (dest / MANIFEST).write_text(json.dumps(manifest))
    result = export_json(out, dest, "--overwrite")
    assert result.exit_code == 0, result.output
    assert database.read_bytes() == b"SQLite format 3\0 the user's database"
    assert outside.read_text() == "keep me"
    assert (dest / "IMG_0001.jpg").read_bytes() == b"the user's photo"
    assert "IMG_0001.jpg: its content is not what rigsfm wrote" in result.output.replace("\n", " ")
    assert "../out/database.db" in result.output
    new = json.loads((dest / MANIFEST).read_text())
    assert new["files"] == ["poses.json"] and new["sha256"] == {"poses.json": sha256_file(dest / "poses.json")}
    # The kept photo is the user's now: the next --overwrite refuses to write among it.
    result = export_json(out, dest, "--overwrite")
    assert result.exit_code == 1 and "holds files rigsfm did not write (IMG_0001.jpg)" in one_error_line(result)


def test_an_export_into_the_folder_of_earlier_exports_says_so(out, tmp_path):
    """``--dest OUT/export`` (the folder holding the default OUT/export/FORMAT folders) holds rigsfm's own earlier
    exports: refused as such, not as 'files rigsfm did not write'; a user's file beside them is still the user's."""
    assert invoke("export", out, "--format", "json").exit_code == 0
    assert invoke("export", out, "--format", "colmap-txt").exit_code == 0
    result = export_json(out, out / "export", "--overwrite")
    line = one_error_line(result)
    assert result.exit_code == 1 and "holds earlier exports in folders of their own (colmap-txt/, json/)" in line, line
    (out / "export" / "notes.txt").write_text("mine")
    line = one_error_line(export_json(out, out / "export", "--overwrite"))
    assert "holds files rigsfm did not write (notes.txt)" in line, line


def test_an_edited_export_file_is_kept_and_named(out, tmp_path):
    dest = tmp_path / "dest"
    assert invoke("export", out, "--format", "colmap-bin", "--dest", dest).exit_code == 0
    assert invoke("export", out, "--format", "colmap-bin", "--dest", dest, "--overwrite").exit_code == 0
    (dest / "cameras.bin").write_bytes(b"edited by hand")
    result = invoke("export", out, "--format", "colmap-bin", "--dest", dest, "--overwrite")
    assert result.exit_code == 1
    assert (f"'{dest / 'cameras.bin'}' is not what an earlier export wrote there (edited or replaced since); move it "
            "away or choose another --dest (nothing was written or removed)") in one_error_line(result)
    assert (dest / "cameras.bin").read_bytes() == b"edited by hand"
    # A stale file of an earlier export, changed since and not written again: kept with a warning.
    (dest / "cameras.bin").unlink()
    (dest / "old.bin").write_bytes(b"mine now")
    manifest = json.loads((dest / MANIFEST).read_text())
    manifest["files"].append("old.bin")
    manifest["sha256"]["old.bin"] = "0" * 64
    (dest / MANIFEST).write_text(json.dumps(manifest))
    result = invoke("export", out, "--format", "colmap-bin", "--dest", dest, "--overwrite")
    assert result.exit_code == 0, result.output
    assert (dest / "old.bin").read_bytes() == b"mine now"
    assert "old.bin: its content is not what rigsfm wrote" in result.output.replace("\n", " ")


def test_an_unchanged_earlier_export_is_replaced_and_its_stale_files_removed(out, tmp_path):
    dest = tmp_path / "dest"
    assert export_json(out, dest).exit_code == 0
    (dest / "stale.json").write_text("{}")  # an earlier export's file, listed with its checksum
    manifest = json.loads((dest / MANIFEST).read_text())
    manifest["files"].append("stale.json")
    manifest["sha256"]["stale.json"] = sha256_file(dest / "stale.json")
    (dest / MANIFEST).write_text(json.dumps(manifest))
    result = export_json(out, dest, "--overwrite")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in dest.iterdir()) == sorted([MANIFEST, "poses.json"])
    assert "warning" not in result.output.lower()


def test_a_listed_link_is_not_followed(out, tmp_path):
    dest = tmp_path / "dest"
    assert export_json(out, dest).exit_code == 0
    target = tmp_path / "precious.txt"
    target.write_text("precious")
    (dest / "link.txt").symlink_to(target)
    manifest = json.loads((dest / MANIFEST).read_text())
    manifest["files"].append("link.txt")
    manifest["sha256"]["link.txt"] = sha256_file(target)  # the checksum of what it points to
    (dest / MANIFEST).write_text(json.dumps(manifest))
    assert export_json(out, dest, "--overwrite").exit_code == 0
    assert (dest / "link.txt").is_symlink() and target.read_text() == "precious"


# --- demo / render_dataset: only the files a render wrote are replaced ---------------------------------------------

SMALL = dict(num_rigs=2, arc_deg=60.0, image_scale=0.25, calibration_noise=False, seed=3)


def tree(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): sha256_file(p) for p in sorted(root.rglob("*")) if p.is_file()}


def test_demo_overwrite_keeps_the_users_files_in_the_scene_folder(tmp_path):
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    options = SceneOptions(**SMALL)
    scene = tmp_path / "demo" / "scene"
    render_dataset(scene, options)
    (scene / "images" / "rig01" / "wide" / "mine.png").write_bytes(b"the user's image")
    (scene / "ground_truth" / "notes.txt").write_text("the user's notes")
    before = tree(scene)
    result = invoke("demo", tmp_path / "demo", "--overwrite", "--num-rigs", 2, "--arc-deg", 60, "--image-scale", 0.25)
    assert result.exit_code == 1
    line = one_error_line(result)
    assert (f"'{scene}' holds files rigsfm did not write there, or changed since (ground_truth/notes.txt, "
            "images/rig01/wide/mine.png); move them away or choose a new folder (nothing was removed)") in line, line
    assert tree(scene) == before

    # Without them, a render over its own earlier render replaces exactly its files (same seed: same bytes).
    (scene / "images" / "rig01" / "wide" / "mine.png").unlink()
    (scene / "ground_truth" / "notes.txt").unlink()
    own = tree(scene)
    render_dataset(scene, options, overwrite=True)
    assert tree(scene) == own

    # One of its own images edited since: refused too, the edit kept.
    edited = scene / "images" / "rig02" / "narrow" / "frame0000.png"
    edited.write_bytes(b"retouched")
    from rigsfm.core.errors import WorkspaceError

    with pytest.raises(WorkspaceError, match=r"changed since \(images/rig02/narrow/frame0000.png\)"):
        render_dataset(scene, options, overwrite=True)
    assert edited.read_bytes() == b"retouched"


def test_a_render_into_a_folder_from_elsewhere_is_refused(tmp_path):
    """A folder without the render's manifest (the user's, or an older version's) is never emptied."""
    from rigsfm.core.errors import WorkspaceError
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    scene = tmp_path / "scene"
    (scene / "images" / "rig01" / "wide").mkdir(parents=True)
    (scene / "images" / "rig01" / "wide" / "frame0000.png").write_bytes(b"a real photo")
    (scene / "rigs.yaml").write_text("my calibration")
    with pytest.raises(WorkspaceError, match=r"holds files rigsfm did not write there"):
        render_dataset(scene, SceneOptions(**SMALL), overwrite=True)
    assert (scene / "images" / "rig01" / "wide" / "frame0000.png").read_bytes() == b"a real photo"
    assert (scene / "rigs.yaml").read_text() == "my calibration"


# --- picker: stale pages add to the newer pairs; every backup generation is kept; a failed save is told -----------

def request(url: str, method: str = "GET", body=None) -> tuple[int, dict]:
    import urllib.error
    import urllib.request

    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method, headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=30) as answer:
            return answer.status, json.loads(answer.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read())


def pair(i: int) -> list[float]:
    return [1.0 + i, 1.0 + i / 2, 2.0 + i, 50.0 - i / 2]


@pytest.fixture()
def picker(tmp_path):
    from rigsfm.pick.server import PickerServer
    from rigsfm.pick.session import PickerSession, picker_image

    paths = picker_images(tmp_path)
    csv = tmp_path / "matches.csv"
    server = PickerServer(PickerSession(picker_image(paths[0], None), picker_image(paths[1], None), csv))
    yield server, csv
    server.close()


def test_stale_pages_add_their_pairs_to_the_newer_ones(picker):
    from rigsfm.run.matching.manual_matches import read_manual_matches

    server, csv = picker
    _, opened = request(server.url + "api/state")  # three pages opened on the empty CSV
    status, first = request(server.url + "api/pairs", "PUT", {"pairs": [pair(i) for i in range(30)],
                                                              "revision": opened["revision"]})
    assert status == 200 and len(first["pairs"]) == 30
    answers = []
    for extra in (30, 31):  # the two stale pages each save one pair
        status, answer = request(server.url + "api/pairs", "PUT", {"pairs": [pair(extra)],
                                                                   "revision": opened["revision"]})
        assert status == 200 and "backup" not in answer
        answers.append(answer)
    rows = read_manual_matches(csv)
    assert [[*r.xy_a, *r.xy_b] for r in rows] == [pair(i) for i in range(32)]
    assert not list(csv.parent.glob("matches.csv*.bak"))
    # The first of them, now behind the second, undoes its pair: only that one goes.
    seen = [[*p["a"], *p["b"]] for p in answers[0]["pairs"]]
    assert seen == [pair(i) for i in range(31)]
    status, answer = request(server.url + "api/pairs", "PUT", {"pairs": seen[:-1], "revision": answers[0]["revision"]})
    assert status == 200 and [[*p["a"], *p["b"]] for p in answer["pairs"]] == [pair(i) for i in (*range(30), 31)]
    assert len(read_manual_matches(csv)) == 31
    # A page of another picker process: refused, nothing changed.
    status, answer = request(server.url + "api/pairs", "PUT", {"pairs": [], "revision": "0123abcd-1"})
    assert status == 409 and "reload the page" in answer["error"] and len(read_manual_matches(csv)) == 31


def test_every_backup_generation_is_kept(picker):
    from rigsfm.run.matching.manual_matches import read_manual_matches

    server, csv = picker
    generations = []
    for count in (30, 5, 3):  # a script saving whole lists, then emptying the CSV each time
        assert request(server.url + "api/pairs", "PUT", {"pairs": [pair(i) for i in range(count)]})[0] == 200
        generations.append(csv.read_bytes())
        status, answer = request(server.url + "api/pairs", "PUT", {"pairs": []})
        assert status == 200 and "backup" in answer
    backups = sorted(csv.parent.glob("matches.csv*.bak"), key=lambda p: p.stat().st_mtime_ns)
    assert [p.read_bytes() for p in backups] == generations
    assert [len(read_manual_matches(p)) for p in backups] == [30, 5, 3]
    assert server.session.backups() == backups


def test_a_csv_folder_made_a_file_is_told_and_nothing_is_claimed_saved(tmp_path):
    """`rigsfm pick` as a user runs it: a save after the CSV's folder became a file fails with a message (no
    traceback); Ctrl-C then names the file keeping the unsaved pairs instead of "nothing finished was lost"."""
    import signal
    import socket
    import time

    from rigsfm.run.matching.manual_matches import read_manual_matches

    picker_images(tmp_path)
    (tmp_path / "sub").mkdir()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "400"}
    process = subprocess.Popen([sys.executable, "-m", "rigsfm", "pick", "images/rig01/wide/f0.png",
                                "images/rig02/wide/f0.png", "--out", "sub/m.csv", "--port", str(port)],
                               cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=as_from_a_terminal)
    try:
        url = f"http://127.0.0.1:{port}/"
        for _ in range(300):
            try:
                _, state = request(url + "api/state")
                break
            except OSError:
                time.sleep(0.1)
        status, state = request(url + "api/pairs", "PUT", {"pairs": [pair(i) for i in range(3)],
                                                           "revision": state["revision"]})
        assert status == 200 and len(read_manual_matches(tmp_path / "sub" / "m.csv")) == 3
        (tmp_path / "sub" / "m.csv").unlink()
        (tmp_path / "sub").rmdir()
        (tmp_path / "sub").write_text("a file where the folder was")
        status, answer = request(url + "api/pairs", "PUT", {"pairs": [pair(i) for i in range(4)],
                                                            "revision": state["revision"]})
        assert status == 500
        assert "cannot save to sub/m.csv: a part of the path is a file, not a folder" in answer["error"]
        rescue = Path(answer["error"].split("are kept in ")[1].split(";")[0])
        assert [[*r.xy_a, *r.xy_b] for r in read_manual_matches(rescue)] == [pair(i) for i in range(4)]
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 1, stderr
    assert "Traceback" not in stderr + stdout and "nothing finished was lost" not in stderr
    assert "pairs in sub/m.csv" not in stdout
    assert (f"the last save of 4 pairs of rig01/wide/f0.png <-> rig02/wide/f0.png failed (cannot save to sub/m.csv: a "
            f"part of the path is a file, not a folder); they are kept in {rescue}") in " ".join(stderr.split())
    rescue.unlink()


# --- the other places rigsfm replaces a folder ----------------------------------------------------------------------

def test_calibrate_refuses_a_report_folder_with_the_users_files_before_calibrating(tmp_path):
    from bad_inputs_table import inputs

    inputs(tmp_path)
    (tmp_path / "board.yaml").write_text("type: chessboard\ninner_corners: [9, 6]\nsquare: 0.03\n")
    mine = tmp_path / "reports" / "rig02" / "my_notes.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("the user's notes")
    result = invoke("calibrate", tmp_path / "images", "--board", tmp_path / "board.yaml", "--out",
                    tmp_path / "new_rigs.yaml", "--report-dir", tmp_path / "reports")
    assert result.exit_code == 1
    assert (f"'{mine.parent}' holds files rigsfm did not write (my_notes.txt); move them away or choose another "
            "--report-dir (nothing was written)") in one_error_line(result)
    assert mine.read_text() == "the user's notes" and not (tmp_path / "new_rigs.yaml").exists()


def test_calibrate_never_replaces_the_users_summary_txt_in_the_report_folder(tmp_path):
    """`--report-dir reports` (or rigs.calibration/ beside a new rigs.yaml) holding the user's own summary.txt: it
    was replaced by the calibration's summary, no --overwrite asked; the rig folders alone were checked."""
    data = Path(__file__).parent / "data" / "opencv-stereo"  # real board images: on the old code it calibrated
    mine = tmp_path / "reports" / "summary.txt"
    mine.parent.mkdir(parents=True)
    mine.write_text("the user's summary of last week's survey")
    result = invoke("calibrate", data / "board", "--board", data / "board.yaml", "--out", tmp_path / "new_rigs.yaml",
                    "--report-dir", tmp_path / "reports")
    assert result.exit_code == 1
    assert (f"'{mine}' is not a summary rigsfm calibrate wrote; move it away or choose another --report-dir (nothing "
            "was written)") in one_error_line(result)
    assert mine.read_text() == "the user's summary of last week's survey" and not (tmp_path / "new_rigs.yaml").exists()


def test_calibrate_replaces_only_its_own_report_of_the_same_rigs_file(tmp_path):
    """`--out c/rigs.yml` after `--out c/rigs.yaml` silently replaced rigs.yaml's report in c/rigs.calibration/ (the
    default folder drops the extension), and a file of the user's named as a report's file was replaced (only names
    were checked). The same command again after a stop (no rigs.yaml yet) still replaces its own report."""
    data = Path(__file__).parent / "data" / "opencv-stereo"
    args = ["calibrate", data / "board", "--board", data / "board.yaml", "--out"]
    assert invoke(*args, tmp_path / "c" / "rigs.yaml").exit_code == 0
    report = tmp_path / "c" / "rigs.calibration" / "rig01" / "report.txt"
    before = tree(tmp_path / "c")
    other = invoke(*args, tmp_path / "c" / "rigs.yml")
    assert other.exit_code == 1
    first = (tmp_path / "c" / "rigs.yaml").resolve()
    assert (f"'{report.parent.parent}' holds the report of another calibration ({first}): pass --overwrite to "
            "replace it or choose another --report-dir (nothing was written)") in one_error_line(other)
    assert tree(tmp_path / "c") == before
    (tmp_path / "c" / "rigs.yaml").unlink()  # as a stop between the report and rigs.yaml leaves it
    assert invoke(*args, tmp_path / "c" / "rigs.yaml").exit_code == 0
    report.write_text("the user's notes")
    mine = invoke(*args, tmp_path / "c" / "rigs.yaml", "--overwrite")
    assert mine.exit_code == 1
    assert (f"'{report}' is not a file rigsfm calibrate wrote (or it changed since); move it away or choose another "
            "--report-dir (nothing was written)") in one_error_line(mine)
    assert report.read_text() == "the user's notes"


def test_a_model_folder_is_replaced_only_while_it_holds_rigsfm_files(out):
    from rigsfm.core.errors import WorkspaceError
    from rigsfm.run.deliver import write_model

    model = pycolmap.Reconstruction(out / "sparse")
    write_model(model, out / "sparse", overwrite=True)  # an earlier model: replaced
    (out / "sparse" / "notes.txt").write_text("the user's notes")
    before = tree(out / "sparse")
    with pytest.raises(WorkspaceError, match=r"sparse' holds files rigsfm did not write there \(notes.txt\); move them "
                                             r"away \(nothing was replaced\)"):
        write_model(model, out / "sparse", overwrite=True)
    assert tree(out / "sparse") == before
    assert sorted(p.name for p in out.iterdir() if p.name.endswith(".tmp") or p.name.endswith(".old")) == []


def test_a_csv_broken_while_the_picker_runs_is_left_as_it_is(picker):
    server, csv = picker
    status, state = request(server.url + "api/pairs", "PUT", {"pairs": [pair(0), pair(1)]})
    assert status == 200
    csv.write_text("image_a;x_a\nhalf an edit\n")  # edited by hand into something that is not a matches CSV
    status, answer = request(server.url + "api/pairs", "PUT", {"pairs": [pair(0), pair(1), pair(2)],
                                                               "revision": state["revision"]})
    assert status == 500 and f"cannot save to {csv}" in answer["error"]
    assert csv.read_text() == "image_a;x_a\nhalf an edit\n"
    rescue = Path(answer["error"].split("are kept in ")[1].split(";")[0])
    from rigsfm.run.matching.manual_matches import read_manual_matches

    assert [[*r.xy_a, *r.xy_b] for r in read_manual_matches(rescue)] == [pair(0), pair(1), pair(2)]
    assert server.session.unsaved is not None and len(server.session.pairs) == 2
    rescue.unlink()


def test_demo_never_replaces_an_accuracy_json_without_overwrite(tmp_path):
    (tmp_path / "accuracy.json").write_text('{"mine": true}')
    result = invoke("demo", tmp_path, "--num-rigs", 2, "--arc-deg", 60, "--image-scale", 0.1)
    assert result.exit_code == 1
    assert f"{tmp_path / 'accuracy.json'} already exists: pass --overwrite" in one_error_line(result)
    assert (tmp_path / "accuracy.json").read_text() == '{"mine": true}' and not (tmp_path / "scene").exists()


# --- one command at a time on OUT -------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", [("export", "--format", "json"), ("associate", "detections.csv")])
def test_export_and_associate_on_an_out_in_use_are_refused_and_write_nothing(out, tmp_path, command):
    """`rigsfm export` and `rigsfm associate` read OUT's model without its lock: a `rigsfm run --overwrite` holding
    OUT could rewrite the model under them (report, run and track are refused)."""
    from rigsfm.core.workspace import Workspace

    (tmp_path / "detections.csv").write_text("image,x,y\nrig01/narrow/f0.png,10,10\n")
    args = [a if a != "detections.csv" else tmp_path / a for a in command[1:]]
    with Workspace(out).lock():
        result = invoke(command[0], out, *args)
    assert result.exit_code == 1
    assert f"'{out}' is in use by process {os.getpid()} (another rigsfm command)" in one_error_line(result)
    assert not (out / "export").exists() and not (out / "associate").exists()
    if command[0] == "export":
        assert invoke(command[0], out, *args).exit_code == 0 and (out / "export" / "json").is_dir()


@pytest.mark.parametrize("command", [("report",), ("export", "--format", "json")])
def test_report_and_export_say_the_run_did_not_finish(out, command):
    """`rigsfm report` and `rigsfm export` on an OUT whose run stopped while delivering (no summary.json, written last)
    read it without a word, though its files may be partly an earlier run's."""
    (out / "summary.json").unlink()  # the run stopped before it
    result = invoke(command[0], out, *command[1:])
    assert result.exit_code == 0, result.output
    said = [line for line in result.output.splitlines() if "did not finish" in line]
    assert len(said) == 1 and "re-run the same `rigsfm run ... --out" in said[0] and "WARNING" in said[0], result.output
    (out / "summary.json").write_text(json.dumps(Summary().to_json()))  # finished
    result = invoke(command[0], out, *command[1:], *(["--overwrite"] if command[0] == "export" else []))
    assert result.exit_code == 0 and "did not finish" not in result.output, result.output


def test_calibrate_overwrite_removes_the_reports_of_rigs_it_no_longer_has_and_only_its_own(tmp_path):
    """`rigsfm calibrate --overwrite` of a rigs.yaml whose calibration had a rig the new one lacks left that rig's
    report folder beside the new report, as if it were this calibration's."""
    from rigsfm.calibrate.report import MANIFEST
    from rigsfm.core.io import sha256_file

    data = Path(__file__).parent / "data" / "opencv-stereo"  # real board images of one rig (rig01)
    args = ["calibrate", data / "board", "--board", data / "board.yaml", "--out", tmp_path / "rigs.yaml"]
    assert invoke(*args).exit_code == 0
    reports = tmp_path / "rigs.calibration"
    line = (reports / "summary.txt").read_text().splitlines()[2]
    assert line.startswith("rig01: wide RMS ")
    # an earlier calibration's rig03 (named in its summary, only its report files), rig04 (the user's notes added)
    # and rig05 (report files alone, named nowhere: not known to be rigsfm's)
    for rig in ("rig03", "rig04", "rig05"):
        (reports / rig).mkdir()
        for name in ("report.txt", "wide_coverage.png"):
            (reports / rig / name).write_bytes((reports / "rig01" / name).read_bytes())
    (reports / "rig04" / "notes.txt").write_text("mine")
    with open(reports / "summary.txt", "a") as summary:
        summary.write(line.replace("rig01", "rig03") + "\n" + line.replace("rig01", "rig04") + "\n")
    manifest = json.loads((reports / MANIFEST).read_text())  # as that calibration recorded its files
    manifest["sha256"] |= {f"{rig}/{name}": sha256_file(reports / rig / name) for rig in ("rig03", "rig04")
                           for name in ("report.txt", "wide_coverage.png")} | {
        "summary.txt": sha256_file(reports / "summary.txt")}
    (reports / MANIFEST).write_text(json.dumps(manifest))
    result = invoke(*args, "--overwrite")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in reports.iterdir()) == [MANIFEST, "rig01", "rig04", "rig05", "summary.txt"]
    assert (reports / "rig04" / "notes.txt").read_text() == "mine" and len(list((reports / "rig05").iterdir())) == 2
    said = [line for line in result.output.splitlines() if "left as they are" in line]
    assert len(said) == 1 and f"'{reports / 'rig04'}', '{reports / 'rig05'}'" in said[0], result.output
    assert "rig03" not in (reports / "summary.txt").read_text()


def test_outputs_made_from_a_replaced_model_are_named(out):
    """`rigsfm run --overwrite` replaced the model under OUT/export, OUT/track and OUT/associate without a word: the
    exports (read by other tools, which nothing in rigsfm shows) kept the earlier result's poses. They are named,
    with the command that makes each again, and kept."""
    from rigsfm.core.workspace import Workspace, model_fingerprint
    from rigsfm.run.deliver import earlier_outputs, earlier_outputs_warning, write_model

    workspace = Workspace(out)
    assert invoke("export", out, "--format", "json").exit_code == 0
    assert invoke("export", out, "--format", "toml").exit_code == 0
    old = model_fingerprint(out / "sparse")
    (out / "track").mkdir()
    (out / "track" / "poses.json").write_text(json.dumps({"reference": {"fingerprint": old}}))
    (out / "associate").mkdir()
    (out / "associate" / ".rigsfm-associate.json").write_text(json.dumps({"model": old, "files": []}))
    assert earlier_outputs(workspace) == [] and earlier_outputs_warning(workspace) is None  # all of this model

    model = pycolmap.Reconstruction(out / "sparse")  # what a `run --overwrite` delivers: another model
    frame = next(iter(model.frames.values()))
    frame.rig_from_world = pycolmap.Rigid3d(frame.rig_from_world.rotation, frame.rig_from_world.translation + 0.01)
    write_model(model, out / "sparse", overwrite=True)
    exported = sorted(tree(out / "export").items())
    warning = earlier_outputs_warning(workspace)
    assert warning is not None and warning.startswith(f"MADE FROM THE EARLIER RESULT: 4 output(s) in {out} ")
    for made, command in ((out / "track", f"rigsfm track {out} NEW_IMAGES --overwrite"),
                          (out / "associate", f"rigsfm associate {out} DETECTIONS --overwrite"),
                          (out / "export" / "json", f"rigsfm export {out} --format json --overwrite"),
                          (out / "export" / "toml", f"rigsfm export {out} --format toml --overwrite")):
        assert f"{made} (`{command}`)" in warning
    assert sorted(tree(out / "export").items()) == exported  # kept as they are
    assert invoke("export", out, "--format", "json", "--overwrite").exit_code == 0
    assert "export/json" not in earlier_outputs_warning(workspace) and "export/toml" in earlier_outputs_warning(workspace)


def test_a_replaced_result_says_what_changed(out):
    """A `run --overwrite` after rigs moved (or on new images) replaced narrow_poses.json without a word on how the
    cameras differ from the result it replaced: the user re-estimating could not tell what changed."""
    from rigsfm.core.summary import Summary
    from rigsfm.run.deliver import changes_from, describe_changes
    from rigsfm.run.deliver import narrow_poses as make_narrow_poses

    model = pycolmap.Reconstruction(out / "sparse")
    earlier = make_narrow_poses(model, metric=True, world={"frame": "floor"})
    assert changes_from(None, earlier) is None  # nothing replaced
    same = changes_from(earlier, earlier)
    assert same["rigs"] == {"rig01": {"rotation_deg": 0.0, "centre_mm": 0.0},
                            "rig02": {"rotation_deg": 0.0, "centre_mm": 0.0}}
    frame = next(f for f in model.frames.values() if f.rig_id == 2)  # rig02 turned 0.3 deg about y, shifted 20 mm
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([0.0, np.sin(np.radians(0.15)), 0.0, np.cos(np.radians(0.15))])),
                            [0.0, 0.0, 0.0])
    moved = turn * frame.rig_from_world
    frame.rig_from_world = pycolmap.Rigid3d(moved.rotation, moved.translation + [0.02, 0.0, 0.0])
    changes = changes_from(earlier, make_narrow_poses(model, metric=True, world={"frame": "floor"}))
    assert changes["rigs"]["rig01"] == {"rotation_deg": 0.0, "centre_mm": 0.0}
    assert changes["rigs"]["rig02"]["rotation_deg"] == pytest.approx(0.3, abs=1e-6)
    assert changes["rigs"]["rig02"]["centre_mm"] > 1.0 and changes["new_images"] == changes["gone_images"] == []
    line = describe_changes(changes)
    assert line.startswith("replaced the earlier result: narrow cameras turned by up to 0.300 deg (rig02) and moved by "
                           "up to ") and "mm (rig02)" in line
    assert Summary.from_json(Summary(replaced=changes).to_json()).replaced == changes  # kept in summary.json
    unscaled = changes_from(earlier, make_narrow_poses(model, metric=False, world={"frame": "floor"}))
    assert unscaled["rigs"]["rig02"]["centre_mm"] is None and "moved by" not in describe_changes(unscaled)
    assert describe_changes(same) == "replaced the earlier result: the same narrow poses (summary.json: replaced)"


def test_a_replaced_result_in_another_world_is_compared_after_aligning(out):
    """A run that found no floor (the mapper's frame), then `--overwrite` with floor markers added (as NO FLOOR FOUND
    advises), said 'narrow cameras turned by up to 17 deg': each camera compared in two different worlds, a rig
    change that is the frames' rotation. Where the worlds are not both the floor frame, the earlier cameras are
    aligned onto the new ones first; two rigs (too few centres to align) are not compared."""
    from rigsfm.run.deliver import changes_from, describe_changes
    from rigsfm.run.deliver import narrow_poses as make_narrow_poses

    model = pycolmap.Reconstruction(out / "sparse")
    floor = make_narrow_poses(model, metric=True, world={"frame": "floor"})
    turned = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(np.array([0.0, np.sin(np.radians(8.5)), 0.0,
                                                               np.cos(np.radians(8.5))])), [1.0, -2.0, 0.5])
    mapping = pycolmap.Reconstruction(model)
    mapping.transform(turned)
    earlier = make_narrow_poses(mapping, metric=True, world={"frame": "mapping"})
    assert max(e["cam_from_world"]["rotation"] != f["cam_from_world"]["rotation"]
               for e, f in zip(earlier["narrow"], floor["narrow"]))  # the worlds differ by 17 deg
    changes = changes_from(earlier, floor)  # two rigs: two narrow centres, no alignment
    assert changes["rigs"] == {} and changes["compared"] is None
    line = describe_changes(changes)
    assert "turned" not in line and "not compared" in line and "mapping" in line
    # three cameras: a third narrow camera beside the two, off their line, in both worlds
    rotation = np.asarray(floor["narrow"][1]["cam_from_world"]["rotation"])
    centre = np.asarray(floor["narrow"][1]["centre"]) + [0.0, 3.0, 1.0]
    moved = dict(floor["narrow"][1], name="rig03/narrow/f0.png", rig="rig03", centre=centre.tolist(),
                 cam_from_world={"rotation": rotation.tolist()})
    before = dict(moved, centre=(turned * centre).tolist(),
                  cam_from_world={"rotation": (rotation @ turned.rotation.matrix().T).tolist()})
    three_now = dict(floor, narrow=[*floor["narrow"], moved])
    three_before = dict(earlier, narrow=[*earlier["narrow"], before])
    changes = changes_from(three_before, three_now)
    assert changes["compared"] == "aligned"
    assert all(v["rotation_deg"] < 1e-6 and v["centre_mm"] < 1e-3 for v in changes["rigs"].values())
    assert describe_changes(changes) == ("replaced the earlier result: the same narrow poses, once the earlier "
                                         "result's world (mapping) is aligned onto this one's (floor) "
                                         "(summary.json: replaced)")
    same = changes_from(floor, floor)  # both in the floor frame: compared as they are
    assert same["compared"] == "floor"


def test_a_demo_stopped_before_its_accuracy_resumes_with_the_same_command(tmp_path):
    """A demo interrupted (or failed) after its render left a scene of its own files: the same command renders it
    again (same bytes) and finishes, instead of refusing the scene folder as 'not empty'."""
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    scene = tmp_path / "demo" / "scene"
    render_dataset(scene, SceneOptions(**SMALL))  # as the stopped demo left it: no run, no accuracy.json
    own = tree(scene)
    result = invoke("demo", tmp_path / "demo", "--num-rigs", 2, "--arc-deg", 60, "--image-scale", 0.25,
                    "--exact-calibration", "--seed", 3)
    assert result.exit_code == 0, result.output
    assert (tmp_path / "demo" / "accuracy.json").is_file()
    assert tree(scene) == own


def test_an_export_into_the_runs_image_folder_is_refused(tmp_path):
    """An export written among the run's images became a folder the next `rigsfm run` on them refused ('folder(s)
    'export' have no rig', 'unexpected 'exp''): refused before anything is written, as run's --out there is."""
    out = workspace(tmp_path)
    summary = Summary()
    summary.inputs.images = str(tmp_path / "images")
    (out / "summary.json").write_text(json.dumps(summary.to_json()))
    for dest in (tmp_path / "images" / "export", tmp_path / "images" / "rig01" / "exp"):
        result = invoke("export", out, "--format", "json", "--dest", dest)
        assert result.exit_code == 1, result.output
        assert f"--dest '{dest}' lies inside the run's image folder" in one_error_line(result)
        assert not dest.exists()
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == ["rig01", "rig02"]
