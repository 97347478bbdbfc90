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
from typer.testing import CliRunner

from rigsfm.cli import app
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
        assert f"sparse/{name} is truncated or damaged ({size} B; " in line, line
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
    assert "points3D.bin is truncated or damaged (24908 B; says 1000000000 3D points but only 24900 B follow)" in \
        done.stderr, done.stderr


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


def test_an_edited_export_file_is_kept_and_named(out, tmp_path):
    dest = tmp_path / "dest"
    assert invoke("export", out, "--format", "colmap-bin", "--dest", dest).exit_code == 0
    assert invoke("export", out, "--format", "colmap-bin", "--dest", dest, "--overwrite").exit_code == 0
    (dest / "cameras.bin").write_bytes(b"edited by hand")
    result = invoke("export", out, "--format", "colmap-bin", "--dest", dest, "--overwrite")
    assert result.exit_code == 1
    assert (f"{dest / 'cameras.bin'} is not what an earlier export wrote there (edited or replaced since); move it "
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
    result = invoke("demo", tmp_path / "demo", "--overwrite", "--num-rigs", 2, "--image-scale", 0.25)
    assert result.exit_code == 1
    line = one_error_line(result)
    assert (f"{scene} holds files rigsfm did not write there, or changed since (ground_truth/notes.txt, "
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
