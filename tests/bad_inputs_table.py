"""The README's table of bad inputs, made by running the command line on each of them.

    python tests/bad_inputs_table.py            # print the table (markdown)
    python tests/bad_inputs_table.py --readme   # and write it into README.md's "When something is wrong"

Each case starts from small valid inputs (two rigs of 64x48 images, rigs.yaml, scale.yaml) or a small finished
workspace (a posed model written with pycolmap), breaks one thing, runs ``rigsfm`` in this process from a
temporary folder (so paths in the messages are relative) and records the first error or warning line verbatim
(the process id and the temporary folder replaced by N and ``/tmp/...``). Cases that need a mount namespace
(a full or read-only disk) run in a child process under ``unshare -m`` and are left out where that is not
allowed. ``tests/test_readme.py`` checks the README's rows against a run of the in-process cases.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
W, H = 64, 48
CAMERA = {"model": "PINHOLE", "width": W, "height": H, "params": [50.0, 50.0, 32.0, 24.0]}
BEGIN, END = "<!-- bad-inputs-table: begin -->", "<!-- bad-inputs-table: end -->"


@dataclass
class Case:
    did: str  # what the user did
    kept: str  # what is kept
    prepare: Callable[[Path], list]  # makes the inputs under the folder, returns the rigsfm arguments
    isolated: str = ""  # a shell prefix (unshare ...) the case needs: run in a child process
    warning: str = ""  # the row shows the first warning with this tag (the run goes on)


def rigs_data() -> dict:
    return {"units": "meters", "rigs": [
        {"name": name, "sensors": {"wide": dict(CAMERA), "narrow": dict(CAMERA)},
         "narrow_from_wide": {"rotation": np.eye(3).tolist(), "translation": [-0.06, 0.0, 0.0]}}
        for name in ("rig01", "rig02")]}


def inputs(root: Path, edit_rigs: Callable[[dict], None] | None = None) -> None:
    rng = np.random.default_rng(0)
    for rig in ("rig01", "rig02"):
        for sensor in ("wide", "narrow"):
            (root / "images" / rig / sensor).mkdir(parents=True)
            cv2.imwrite(str(root / "images" / rig / sensor / "f0.png"), rng.integers(0, 255, (H, W), dtype=np.uint8))
    data = rigs_data()
    if edit_rigs:
        edit_rigs(data)
    (root / "rigs.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    (root / "scale.yaml").write_text(yaml.safe_dump({"camera_distance": [
        {"a": "rig01/wide", "b": "rig02/wide", "meters": 12.0}]}))


RUN = ["run", "images", "--rigs", "rigs.yaml", "--out", "out"]


def with_rigs(edit: Callable[[dict], None]) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root, edit)
        return RUN
    return prepare


def with_scale(scale: dict) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        (root / "scale.yaml").write_text(yaml.safe_dump(scale))
        return [*RUN, "--scale", "scale.yaml"]
    return prepare


def with_matches(text: str | bytes) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        path = root / "matches.csv"
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        return [*RUN, "--manual-matches", "matches.csv"]
    return prepare


def with_offsets(text: str) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        (root / "offsets.yaml").write_text(text)
        return [*RUN, "--frame-offsets", "offsets.yaml"]
    return prepare


def with_images(edit: Callable[[Path], None], extra: tuple = ()) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        edit(root / "images")
        return [*RUN, *extra]
    return prepare


def one_rig(root: Path) -> list:
    inputs(root, lambda data: data["rigs"].pop())
    shutil.rmtree(root / "images" / "rig02")
    return RUN


def tagged_jpegs(images: Path) -> None:
    """Every image as a JPEG of the same pixels tagged EXIF Orientation=6, as a camera mounted on its side writes
    them."""
    from support import write_tagged

    for path in sorted(images.rglob("*.png")):
        write_tagged(path.with_suffix(".jpg"), cv2.imread(str(path), cv2.IMREAD_UNCHANGED), 6)
        path.unlink()


def calibrated_turned(root: Path) -> list:
    """Tagged JPEGs with a rigs.yaml made on the turned pixels (48x64), as OpenCV's default imread gives them."""
    def turn(data: dict) -> None:
        for rig in data["rigs"]:
            for sensor in ("wide", "narrow"):
                rig["sensors"][sensor] = dict(CAMERA, width=H, height=W)
    inputs(root, turn)
    tagged_jpegs(root / "images")
    return RUN


def with_database(make: Callable[[Path], None]) -> Callable[[Path], list]:
    """The inputs and an OUT of an earlier run whose ``database.db`` is what ``make(path)`` leaves."""
    def prepare(root: Path) -> list:
        from rigsfm.core.workspace import MARKER

        inputs(root)
        (root / "out").mkdir()
        (root / "out" / MARKER).touch()
        make(root / "out" / "database.db")
        return RUN
    return prepare


def empty_colmap_database(path: Path) -> None:
    """What COLMAP's next stage leaves when database.db is removed under a run: it opens the path, an empty one."""
    import pycolmap

    pycolmap.Database.open(path).close()


def foreign_database(path: Path) -> None:
    import sqlite3

    with contextlib.closing(sqlite3.connect(path)) as connection, connection:
        connection.execute("CREATE TABLE notes (text TEXT)")


def workspace(root: Path) -> Path:
    """A small finished workspace: a posed two-rig model, narrow_poses.json and summary-less."""
    import pycolmap

    from rigsfm.core.rig import RigCalibration, add_posed_rig
    from rigsfm.core.workspace import MARKER
    from rigsfm.run.deliver import write_narrow_poses

    inputs(root)
    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=CAMERA["params"])
    rig = RigCalibration("rig01", camera, camera, pycolmap.Rigid3d(pycolmap.Rotation3d(), [-0.06, 0.0, 0.0]))
    model = pycolmap.Reconstruction()
    for k, name in enumerate(("rig01", "rig02")):
        add_posed_rig(model, k + 1, RigCalibration(name, rig.wide, rig.narrow, rig.narrow_from_wide),
                      pycolmap.Rigid3d(pycolmap.Rotation3d(), [3.0 * k, 0.0, 0.0]),
                      [{"wide": f"{name}/wide/f0.png", "narrow": f"{name}/narrow/f0.png"}])
    out = root / "out"
    (out / "sparse").mkdir(parents=True)
    (out / MARKER).touch()
    model.write(out / "sparse")
    write_narrow_poses(model, out / "narrow_poses.json", metric=True, overwrite=True)
    return out


def on_workspace(edit: Callable[[Path], None], args: list) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        edit(workspace(root))
        return args
    return prepare


def exported(out: Path) -> Path:
    """An earlier `export --format json --dest exported` next to the workspace."""
    from rigsfm.inspect.export import export
    from rigsfm.inspect.options import ExportFormat, ExportOptions

    return export(out, ExportOptions(format=ExportFormat.JSON, dest=out.parent / "exported"))


def edited_export(out: Path) -> None:
    (exported(out) / "poses.json").write_text('{"edited": "by hand"}')


def forged_manifest(out: Path) -> None:
    import json

    from rigsfm.inspect.export import MANIFEST

    manifest = exported(out) / MANIFEST
    data = json.loads(manifest.read_text())
    manifest.write_text(json.dumps({**data, "files": [*data["files"], "../out/database.db"]}))
    (out / "database.db").write_bytes(b"SQLite format 3\0")


def users_scene(root: Path) -> list:
    (root / "demo" / "scene" / "images").mkdir(parents=True)
    (root / "demo" / "scene" / "images" / "holiday.jpg").write_bytes(b"a photo")
    return ["demo", "demo", "--overwrite", "--num-rigs", "2", "--arc-deg", "60", "--image-scale", "0.1"]


def report_dir_in_use(root: Path) -> list:
    inputs(root)
    (root / "board.yaml").write_text("type: chessboard\ninner_corners: [9, 6]\nsquare: 0.03\n")
    (root / "reports" / "rig01").mkdir(parents=True)
    (root / "reports" / "rig01" / "notes.txt").write_text("mine")
    return ["calibrate", "images", "--board", "board.yaml", "--out", "new_rigs.yaml", "--report-dir", "reports"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_HELD: list = []


def port_in_use(root: Path) -> list:
    inputs(root)
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen()
    _HELD.append(held)
    return ["pick", "images/rig01/wide/f0.png", "images/rig02/wide/f0.png", "--out", "matches.csv", "--port",
            str(held.getsockname()[1])]


def out_in_use(root: Path) -> list:
    from rigsfm.core.workspace import Workspace

    inputs(root)
    lock = Workspace(root / "out").lock()
    lock.__enter__()
    _HELD.append(lock)
    return RUN


def explore_workspace(edit: Callable[[Path], None] | None, args: list, images: bool = True) -> Callable[[Path], list]:
    """The small workspace with its poses declared in the floor frame (as a run with a floor writes them)."""
    import json

    def prepare(root: Path) -> list:
        out = workspace(root)
        poses = json.loads((out / "narrow_poses.json").read_text())
        poses["world"] = {"frame": "floor"}
        (out / "narrow_poses.json").write_text(json.dumps(poses))
        if edit is not None:
            edit(out)
        return ["explore", "out", *(["--images", "images"] if images else []), *args]
    return prepare


def one_narrow_image(out: Path) -> None:
    """rig02's frame left unregistered: no frame has narrow images of two rigs."""
    import pycolmap

    model = pycolmap.Reconstruction(out / "sparse")
    model.deregister_frame(model.find_image_with_name("rig02/narrow/f0.png").frame_id)
    model.write(out / "sparse")


def explore_port_in_use(root: Path) -> list:
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen()
    _HELD.append(held)
    return explore_workspace(None, ["--port", str(held.getsockname()[1])])(root)


def with_pairs(count: int) -> str:
    rows = [f"rig01/wide/f0.png,{10 + 4 * k},{5 + 3 * k},rig02/wide/f0.png,{12 + 4 * k},{6 + 2 * k}"
            for k in range(count)]
    return "image_a,x_a,y_a,image_b,x_b,y_b\n" + "\n".join(rows) + "\n"


DETECTIONS = "image,x,y\nrig01/narrow/f0.png,10.5,20.25\nrig02/narrow/f0.png,30,22\n"
SIZED_DETECTIONS = "image,x,y,radius\nrig01/narrow/f0.png,10.5,20.25,5.5\nrig02/narrow/f0.png,30,22,6\n"


def with_detections(text: str | bytes) -> Callable[[Path], list]:
    """``rigsfm associate`` on the small workspace with this detections CSV."""
    def prepare(root: Path) -> list:
        workspace(root)
        (root / "heads.csv").write_bytes(text if isinstance(text, bytes) else text.encode())
        return ["associate", "out", "heads.csv", "--out", "persons"]
    return prepare


def users_association_folder(root: Path) -> list:
    """``rigsfm associate --overwrite`` into a folder holding the user's notes."""
    args = with_detections(DETECTIONS)(root)
    (root / "persons").mkdir()
    (root / "persons" / "notes.txt").write_text("x")
    return [*args, "--overwrite"]


def rotate(data: dict, key: str, value) -> None:
    data["rigs"][1]["narrow_from_wide"][key] = value


def lens(model: str, params: list) -> Callable[[Path], list]:
    return with_rigs(lambda d: d["rigs"][0]["sensors"].update(wide=dict(CAMERA, model=model, params=params)))


def with_rigs_text(edit: Callable[[str], str]) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        (root / "rigs.yaml").write_text(edit((root / "rigs.yaml").read_text()))
        return RUN
    return prepare


def with_scale_text(text: str) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        (root / "scale.yaml").write_text(text)
        return [*RUN, "--scale", "scale.yaml"]
    return prepare


def rigs_replaced(make: Callable[[Path], None]) -> Callable[[Path], list]:
    def prepare(root: Path) -> list:
        inputs(root)
        (root / "rigs.yaml").unlink()
        make(root / "rigs.yaml")
        return RUN
    return prepare


CASES = [
    # --- rigs.yaml
    Case("rigs.yaml is not where `--rigs` says", "nothing is written",
         lambda root: (inputs(root), [*RUN[:2], "--rigs", "rig.yaml", "--out", "out"])[1]),
    Case("rigs.yaml with a syntax error", "nothing is written",
         lambda root: (inputs(root), (root / "rigs.yaml").write_text("rigs: [name: rig01"), RUN)[2]),
    Case("a key misspelt in rigs.yaml (`tranlsation`)", "nothing is written",
         with_rigs(lambda d: d["rigs"][1]["narrow_from_wide"].update(
             tranlsation=d["rigs"][1]["narrow_from_wide"].pop("translation")))),
    Case("E^sl translation in millimetres (-60 instead of -0.06)", "nothing is written",
         with_rigs(lambda d: rotate(d, "translation", [-60.0, 0.0, 0.0]))),
    Case("`units: millimeters` in rigs.yaml", "nothing is written", with_rigs(lambda d: d.update(units="millimeters"))),
    Case("a principal point outside the image (cx for another resolution)", "nothing is written",
         with_rigs(lambda d: d["rigs"][0]["sensors"].update(wide=dict(CAMERA, params=[50.0, 50.0, 130.0, 24.0])))),
    Case("the focal length in millimetres (8 instead of 1818 px)", "nothing is written",
         with_rigs(lambda d: d["rigs"][0]["sensors"].update(narrow=dict(CAMERA, params=[4.0, 4.0, 32.0, 24.0])))),
    Case("an unknown camera model (`PINHOL`)", "nothing is written",
         with_rigs(lambda d: d["rigs"][0]["sensors"].update(wide=dict(CAMERA, model="PINHOL")))),
    Case("OPENCV with the 4 parameters of PINHOLE", "nothing is written",
         with_rigs(lambda d: d["rigs"][0]["sensors"].update(narrow=dict(CAMERA, model="OPENCV")))),
    Case("a rotation rounded to 2 decimals", "nothing is written",
         with_rigs(lambda d: rotate(d, "rotation", [[1, 0, 0], [0, 0.98, -0.17], [0, 0.17, 0.98]]))),
    Case("a rotation that is a reflection (det -1)", "nothing is written",
         with_rigs(lambda d: rotate(d, "rotation", [[1, 0, 0], [0, 1, 0], [0, 0, -1]]))),
    Case("a calibration sigma of 8 degrees for E^sl's rotation", "nothing is written",
         with_rigs(lambda d: rotate(d, "sigma_rotation_deg", [0.01, 8.0, 0.01]))),
    Case("two rigs with the same name", "nothing is written",
         with_rigs(lambda d: d["rigs"][1].update(name="rig01"))),
    Case("a key given twice in rigs.yaml (`wide:` twice in a rig)", "nothing is written",
         with_rigs_text(lambda text: text.replace("    wide:", "    wide:\n      model: PINHOLE\n    wide:", 1))),
    Case("a rig named `1` (YAML reads a number)", "nothing is written",
         with_rigs_text(lambda text: text.replace("name: rig01", "name: 1", 1))),
    Case("an image width written as a 300-digit integer", "nothing is written",
         with_rigs_text(lambda text: text.replace(f"width: {W}", "width: " + "9" * 300, 1))),
    Case("EUCM with alpha = 7 (its domain is 0-1)", "nothing is written",
         lens("EUCM", [50.0, 50.0, 32.0, 24.0, 7.0, 1.0])),
    Case("FOV with a negative omega", "nothing is written", lens("FOV", [50.0, 50.0, 32.0, 24.0, -0.9])),
    Case("OPENCV with k1 = 1e6", "nothing is written", lens("OPENCV", [50.0, 50.0, 32.0, 24.0, 1e6, 0.0, 0.0, 0.0])),
    Case("OPENCV with k1 = 900 (bends the image centre)", "nothing is written",
         lens("OPENCV", [50.0, 50.0, 32.0, 24.0, 900.0, 0.0, 0.0, 0.0])),
    Case("`--rigs` a folder", "nothing is written", rigs_replaced(lambda p: p.mkdir())),
    Case("`--rigs` a symbolic link loop", "nothing is written", rigs_replaced(lambda p: os.symlink(p.name, p))),
    Case("`--rigs /dev/zero`", "nothing is written", rigs_replaced(lambda p: os.symlink("/dev/zero", p))),
    Case("a rigs.yaml of 40 MiB", "nothing is written",
         with_rigs_text(lambda text: text + ("# " + "x" * 1022 + "\n") * (40 * 1024))),
    # --- images
    Case("the image folder misspelt", "nothing is written", lambda root: (inputs(root), ["run", "image", *RUN[2:]])[1]),
    Case("an image folder named with brackets (`img[/]x`) that does not exist", "nothing is written",
         lambda root: (inputs(root), ["run", "img[/]x", *RUN[2:]])[1]),
    Case("a folder under IMAGES that is not a rig of rigs.yaml", "nothing is written",
         with_images(lambda images: shutil.copytree(images / "rig02", images / "rig03"))),
    Case("a rig of rigs.yaml without its folder", "nothing is written",
         with_images(lambda images: shutil.rmtree(images / "rig02"))),
    Case("`rigsfm run` on one rig (its board images, say)", "nothing is written", one_rig),
    Case("an image at another resolution than calibrated", "nothing is written",
         with_images(lambda images: cv2.imwrite(str(images / "rig02" / "wide" / "f0.png"),
                                                np.zeros((H * 2, W * 2), np.uint8)))),
    Case("JPEGs tagged EXIF Orientation=6 (a camera on its side), rigs.yaml made on the pixels as stored",
         "nothing is written", with_images(tagged_jpegs)),
    Case("the same JPEGs with a rigs.yaml made on the turned images (48x64)", "nothing is written", calibrated_turned),
    Case("a corrupt image file", "nothing is written",
         with_images(lambda images: (images / "rig01" / "narrow" / "f0.png").write_bytes(b"\x89PNG\r\n\x1a\n cut"))),
    Case("a narrow image without its wide image", "nothing is written",
         with_images(lambda images: (images / "rig02" / "narrow" / "f0.png").rename(
             images / "rig02" / "narrow" / "f1.png"))),
    Case("a narrow image named with brackets (`frame[cam].png`) without its wide image", "nothing is written",
         with_images(lambda images: (images / "rig02" / "narrow" / "f0.png").rename(
             images / "rig02" / "narrow" / "frame[cam].png"))),
    Case("images directly in IMAGES/ instead of IMAGES/<rig>/<sensor>/", "nothing is written",
         with_images(lambda images: shutil.copy(images / "rig01" / "wide" / "f0.png", images / "f0.png"))),
    Case("a rig without a narrow folder (a warning: the run goes on and exits 0 when it finishes; this table's "
         "64x48 noise images exit 1 later, at mapping)", "the run goes on; its narrow camera gets no pose",
         with_images(lambda images: shutil.rmtree(images / "rig02" / "narrow")), warning="NO NARROW IMAGES"),
    Case("a FIFO (named pipe) named like an image in an image folder", "nothing is written",
         with_images(lambda images: os.mkfifo(images / "rig02" / "wide" / "f1.png"))),
    Case("`--out` inside the image folder (`--out images/out`)", "nothing is written",
         lambda root: (inputs(root), [*RUN[:4], "--out", "images/out"])[1]),
    # --- scale.yaml
    Case("scale.yaml naming a camera that does not exist", "nothing is written",
         with_scale({"camera_distance": [{"a": "rig01/wide", "b": "rig03/wide", "meters": 12.0}]})),
    Case("a known-length end point outside its image", "nothing is written",
         with_scale({"known_length": [{"meters": 2.0, "observations": [
             {"image": "rig01/wide/f0.png", "a": [10, 10], "b": [20, 12]},
             {"image": "rig02/wide/f0.png", "a": [30, 20], "b": [80, 22]}]}]})),
    Case("a bar whose two ends were clicked on one point", "nothing is written",
         with_scale({"known_length": [{"meters": 2.0, "observations": [
             {"image": "rig01/wide/f0.png", "a": [10, 10], "b": [20, 12]},
             {"image": "rig02/wide/f0.png", "a": [30, 20], "b": [30, 20]}]}]})),
    Case("a distance in scale.yaml that is not a number (`meters: \"[/]\"`)", "nothing is written",
         with_scale({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": "[/]"}]})),
    Case("a misspelt key in scale.yaml (`camera_distances`)", "nothing is written",
         with_scale({"camera_distances": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 12.0}]})),
    Case("`camera_distance` given twice in scale.yaml", "nothing is written",
         with_scale_text("camera_distance: [{a: rig01/wide, b: rig02/wide, meters: 12.0}]\n"
                         "camera_distance: [{a: rig01/wide, b: rig02/wide, meters: 12.5}]\n")),
    Case("a decimal comma in scale.yaml (`meters: 25,98`)", "nothing is written",
         with_scale_text("camera_distance: [{a: rig01/wide, b: rig02/wide, meters: 25,98}]\n")),
    Case("a rangefinder distance of 1e308 m", "nothing is written",
         with_scale({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 1e308}]})),
    Case("a rangefinder distance of 0 m", "nothing is written",
         with_scale({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 0}]})),
    Case("a rangefinder sigma of 1e-300 m", "nothing is written",
         with_scale({"camera_distance": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 12.0, "sigma": 1e-300}]})),
    Case("a distance between the two sensors of one rig", "nothing is written",
         with_scale({"camera_distance": [{"a": "rig01/wide", "b": "rig01/narrow", "meters": 0.06}]})),
    # --- matches.csv
    Case("matches.csv saved by a spreadsheet with `;` separators", "nothing is written",
         with_matches(with_pairs(8).replace(",", ";"))),
    Case("matches.csv in Latin-1 with an accented file name", "nothing is written",
         with_matches(with_pairs(8).replace("f0.png", "fé.png").encode("latin-1"))),
    Case("matches.csv naming an image that does not exist", "nothing is written",
         with_matches(with_pairs(8).replace("rig02/wide/f0.png", "rig02/wide/f0.jpg"))),
    Case("matches.csv with 5 correspondences for a pair", "nothing is written", with_matches(with_pairs(5))),
    # --- rigsfm associate: the detections CSV
    Case("a detections CSV naming an image the run does not have", "nothing is written",
         with_detections(DETECTIONS.replace("rig02/narrow", "rig03/narrow"))),
    Case("a detection outside its image", "nothing is written", with_detections(DETECTIONS.replace(",30,", ",70,"))),
    Case("a detection with NaN coordinates", "nothing is written", with_detections(DETECTIONS.replace("30,22", "nan,22"))),
    Case("a detections CSV without its y column", "nothing is written",
         with_detections("image,x\nrig01/narrow/f0.png,10\n")),
    Case("a detections CSV saved with `;` separators", "nothing is written",
         with_detections(DETECTIONS.replace(",", ";"))),
    Case("a detection repeated on two rows", "nothing is written",
         with_detections(DETECTIONS + "rig01/narrow/f0.png,10.50,20.250\n")),  # the same point, other digits
    Case("detections in a frame the run was not given", "nothing is written",
         with_detections(DETECTIONS + "rig01/narrow/f1.png,10,20\n")),
    Case("`associate --poses-from` a frame the run does not have", "nothing is written",
         lambda root: [*with_detections(DETECTIONS)(root), "--poses-from", "f9.png"]),
    Case("a detection radius of 0 px", "nothing is written",
         with_detections(SIZED_DETECTIONS.replace(",22,6", ",22,0"))),
    Case("a detection radius wider than half its image", "nothing is written",
         with_detections(SIZED_DETECTIONS.replace(",22,6", ",22,5000"))),
    Case("a detections CSV with a radius on some rows of a frame and not on others", "nothing is written",
         with_detections(SIZED_DETECTIONS.replace(",22,6", ",22,"))),
    Case("`rigsfm associate --heights 2.1-1.0`", "nothing is written",
         lambda root: [*with_detections(DETECTIONS)(root), "--heights", "2.1-1.0"]),
    Case("`rigsfm associate` on a run without a floor frame", "nothing is written",
         with_detections(b"\xef\xbb\xbf" + DETECTIONS.encode())),
    # --- frame offsets
    Case("`--frame-offsets` naming a rig that is not in rigs.yaml", "nothing is written",
         with_offsets("rig09: 1\n")),
    Case("`--frame-offsets` written `rig02=1`", "nothing is written", with_offsets("rig02=1\n")),
    Case("`--frame-offsets` with half a frame (`rig02: 0.5`)", "nothing is written", with_offsets("rig02: 0.5\n")),
    Case("`--frame-offsets` beyond the recording (3 frames off, one frame recorded)", "nothing is written",
         with_offsets("rig02: 3\n")),
    # --- options
    Case("`--max-ratio 0`", "nothing is written", lambda root: (inputs(root), [*RUN, "--max-ratio", "0"])[1]),
    Case("`--max-ratio nan`", "nothing is written", lambda root: (inputs(root), [*RUN, "--max-ratio", "nan"])[1]),
    Case("`--incremental-time-limit 2147483648` (beyond COLMAP's int)", "nothing is written",
         lambda root: (inputs(root), [*RUN, "--incremental-time-limit", "2147483648"])[1]),
    Case("`--plane-height nan`", "nothing is written", lambda root: (inputs(root), [*RUN, "--plane-height", "nan"])[1]),
    Case("`demo --image-scale 0.05` (too small to register)", "nothing is written",
         lambda root: ["demo", "demo", "--image-scale", "0.05"]),
    Case("`track --translation-threshold-mm inf`", "nothing is written",
         on_workspace(lambda out: None, ["track", "out", "images", "--translation-threshold-mm", "inf"])),
    Case("`--device cuda` with pycolmap's CPU build", "nothing is written",
         lambda root: (inputs(root), [*RUN, "--device", "cuda"])[1]),
    # --- the workspace
    Case("`--out` a folder with other files in it", "the folder is untouched",
         lambda root: (inputs(root), (root / "out").mkdir(), (root / "out" / "thesis.tex").write_text("x"), RUN)[3]),
    Case("`rigsfm run` again on a finished OUT without `--overwrite`", "the result is untouched",
         on_workspace(lambda out: (out / "summary.json").write_text("{}"), RUN)),  # summary.json: finished
    Case("a second `rigsfm run` on an OUT in use", "the first run goes on undisturbed", out_in_use),
    Case("OUT on a full disk", "finished stages are kept: free space and re-run to resume",
         lambda root: RUN, isolated="mount -t tmpfs -o size=300k tmpfs out &&"),
    Case("OUT on a read-only file system", "nothing is written",
         lambda root: RUN, isolated="mount -t tmpfs -o ro tmpfs out &&"),
    Case("a damaged `database.db` in OUT (random bytes, cut short)", "the database is made again, with its features "
         "and matches; the run goes on", with_database(lambda db: db.write_bytes(b"not a database\n" * 300)),
         warning="database.db"),
    Case("`database.db` removed while a run matched (COLMAP then leaves an empty one)", "the database is made again, "
         "with its features and matches; the run goes on", with_database(empty_colmap_database), warning="database.db"),
    Case("a `database.db` in OUT that is not COLMAP's", "the file is untouched", with_database(foreign_database)),
    Case("a damaged `database.db` for `rigsfm track`", "nothing is written",
         on_workspace(lambda out: (out / "database.db").write_bytes(b"not a database\n" * 300), ["track", "out", "images"])),
    Case("`export --dest OUT` (the workspace itself)", "the workspace is untouched",
         on_workspace(lambda out: None, ["export", "out", "--format", "json", "--dest", "out", "--overwrite"])),
    Case("`export --dest` a folder with other files", "the folder is untouched",
         on_workspace(lambda out: (out.parent / "notes").mkdir() or (out.parent / "notes" / "a.txt").write_text("x"),
                      ["export", "out", "--format", "json", "--dest", "notes", "--overwrite"])),
    Case("`associate --overwrite` into a folder with other files", "the folder is untouched",
         users_association_folder),
    Case("`associate --out OUT` (the workspace itself)", "the workspace is untouched",
         lambda root: [*with_detections(DETECTIONS)(root)[:-1], "out", "--overwrite"]),
    Case("`rigsfm export` given a demo's folder instead of its run/", "nothing is written",
         on_workspace(lambda out: (out.parent / "demo").mkdir() or out.rename(out.parent / "demo" / "run"),
                      ["export", "demo", "--format", "json"])),
    Case("`rigsfm export` given a file of the run (`out/narrow_poses.json`) instead of its folder",
         "nothing is written", on_workspace(lambda out: None, ["export", "out/narrow_poses.json", "--format", "json"])),
    Case("`export --format wildtrack --images` of a run stopped before its summary.json", "nothing is written",
         on_workspace(lambda out: None, ["export", "out", "--format", "wildtrack", "--images"])),
    Case("`rigsfm track OUT OUT` (the workspace given for the new images)", "nothing is written",
         on_workspace(lambda out: None, ["track", "out", "out"])),
    Case("`rigsfm report` given the image folder instead of OUT", "nothing is written",
         lambda root: (inputs(root), ["report", "images"])[1]),
    Case("`rigsfm report` on a folder without a result", "nothing is written",
         lambda root: ((root / "notes").mkdir(), ["report", "notes"])[1]),
    Case("a truncated `sparse/images.bin`", "nothing is written",
         on_workspace(lambda out: (out / "sparse" / "images.bin").write_bytes(
             (out / "sparse" / "images.bin").read_bytes()[:30]), ["report", "out"])),
    Case("a `sparse/points3D.bin` cut short", "nothing is written",
         on_workspace(lambda out: (out / "sparse" / "points3D.bin").write_bytes(
             (out / "sparse" / "points3D.bin").read_bytes()[:4]), ["report", "out"])),
    Case("`export --overwrite` over an exported file edited since", "the edited file and the export are untouched",
         on_workspace(edited_export, ["export", "out", "--format", "json", "--dest", "exported", "--overwrite"])),
    Case("`export --overwrite` with a manifest listing `../out/database.db` (a warning: the export goes on)",
         "every file outside the export, and every listed file not as rigsfm wrote it",
         on_workspace(forged_manifest, ["export", "out", "--format", "json", "--dest", "exported", "--overwrite"]),
         warning="database.db"),
    Case("`demo --overwrite` on a scene folder holding the user's files", "the scene folder is untouched",
         users_scene),
    Case("`calibrate --report-dir` whose rig folder holds other files", "nothing is written",
         report_dir_in_use),
    Case("a damaged `narrow_poses.json`", "nothing is written",
         on_workspace(lambda out: (out / "narrow_poses.json").write_text('{"narrow": ['), ["report", "out"])),
    Case("`rigsfm view` on a machine without a display", "nothing is written",
         on_workspace(lambda out: None, ["view", "out"])),
    Case("`rigsfm pick --port` a port already in use", "the CSV is untouched", port_in_use),
    Case("`rigsfm explore --frame` a frame the result does not hold", "nothing is written",
         explore_workspace(None, ["--frame", "f9.png"])),
    Case("`rigsfm explore` on a result without narrow images of one frame from two rigs", "nothing is written",
         explore_workspace(one_narrow_image, [])),
    Case("`rigsfm explore --port` a port already in use", "the labels CSV is untouched", explore_port_in_use),
    Case("`rigsfm explore --check` a CSV with rows of another format or result (a warning)",
         "the CSV is untouched; its other rows are checked",
         explore_workspace(lambda out: (out.parent / "labels.csv").write_text(
             "image,x,y,person\nrig01/narrow/f0.png,10,10,p1\nrig02/narrow/f0.png,12,10,p1\nrig09/narrow/f0.png,1,1,p1\n"),
             ["--check", "labels.csv"]), warning="FOREIGN ROWS"),
    Case("`rigsfm explore` where the run's IMAGES folder is gone", "nothing is written",
         explore_workspace(lambda out: (out / "summary.json").write_text(
             '{"inputs": {"images": "/media/usb/IMAGES", "num_rigs": 2}}'), [], images=False)),
    Case("`rigsfm explore --heights 2-1`", "nothing is written", explore_workspace(None, ["--heights", "2-1"])),
    Case("`track --executor ray --address` where no Ray cluster listens", "nothing is written",
         on_workspace(lambda out: None, ["track", "out", "images", "--executor", "ray", "--address",
                                         f"127.0.0.1:{free_port()}"])),
]


def first_message(output: str, warning: str = "") -> str:
    """The error line (with ``warning``: the first warning line with that tag), else the usage error, of a
    command's output."""
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    warnings = [re.sub(r"^WARNING\s+", "warning: ", line) for line in lines
                if line.startswith("WARNING") and warning and warning in line]
    if warnings:
        return warnings[0]
    for prefix in ("error:", "internal error:"):
        found = [line for line in lines if line.startswith(prefix)]
        if found:
            return found[0]
    usage = [line.strip("│ ").strip().removeprefix("Error: ") for line in lines if "Invalid value" in line]
    return usage[0] if usage else (lines[-1] if lines else "")


def normalise(text: str, root: Path) -> str:
    text = text.replace(str(root.resolve()) + "/", "").replace(str(root) + "/", "")
    text = re.sub(r"process \d+", "process N", text)
    text = re.sub(r"127\.0\.0\.1:\d+", "127.0.0.1:PORT", text)
    text = re.sub(r"--port \d+", "--port PORT", text)
    return re.sub(r"/tmp/rigsfm-error-\w+\.txt", "/tmp/rigsfm-error-....txt", text)


def run_case(case: Case, root: Path) -> tuple[int, str] | None:
    """(exit code, message) of one case in the folder ``root`` (None when it cannot run here)."""
    from typer.testing import CliRunner

    from rigsfm.cli import app

    root.mkdir(parents=True)
    args = [str(a) for a in case.prepare(root)]
    if case.isolated:
        inputs(root)
        (root / "out").mkdir()
        if subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode != 0:
            return None
        env = {**os.environ, "PYTHONPATH": str(REPO), "COLUMNS": "400", "OMP_NUM_THREADS": "1"}
        command = f"cd {root} && {case.isolated} {sys.executable} -m rigsfm {' '.join(args)}"
        done = subprocess.run(["unshare", "-m", "sh", "-c", command], capture_output=True, text=True, env=env)
        return done.returncode, normalise(first_message(done.stderr + done.stdout, case.warning), root)
    saved = os.getcwd()
    os.chdir(root)
    try:
        env = {"COLUMNS": "400", "DISPLAY": None, "WAYLAND_DISPLAY": None}
        result = CliRunner().invoke(app, args, env=env)
    finally:
        os.chdir(saved)
        while _HELD:
            held = _HELD.pop()
            if isinstance(held, socket.socket):
                held.close()
            else:
                held.__exit__(None, None, None)
    return result.exit_code, normalise(first_message(result.output, case.warning), root)


def rows(cases=CASES, *, isolated: bool = True) -> list[tuple[str, int, str, str]]:
    out = []
    with tempfile.TemporaryDirectory(prefix="rigsfm-bad-inputs-") as tmp:
        for k, case in enumerate(cases):
            if case.isolated and not isolated:
                continue
            done = run_case(case, Path(tmp) / f"case{k:02d}")
            if done is not None:
                out.append((case.did, done[0], done[1], case.kept))
    return out


def markdown(table_rows) -> str:
    def cell(text) -> str:
        return str(text).replace("|", "\\|")

    lines = ["| what you did | exit | what rigsfm says (verbatim) | what is kept |", "| --- | --- | --- | --- |"]
    lines += [f"| {cell(did)} | {code} | `` {cell(message)} `` | {cell(kept)} |" for did, code, message, kept in table_rows]
    return "\n".join(lines)


def readme_rows(readme: str) -> list[tuple[str, int, str, str]]:
    """The rows of the table between the markers in README.md."""
    block = readme.split(BEGIN, 1)[1].split(END, 1)[0]
    found = []
    for line in block.splitlines()[2:]:
        match = re.match(r"^\| (.*) \| (\d+) \| `` (.*) `` \| (.*) \|$", line.strip())
        if match:
            did, code, message, kept = (g.replace("\\|", "|") for g in match.groups())
            found.append((did, int(code), message, kept))
    return found


def write_readme(table: str) -> None:
    path = REPO / "README.md"
    text = path.read_text()
    before, rest = text.split(BEGIN, 1)
    after = rest.split(END, 1)[1]
    path.write_text(f"{before}{BEGIN}\n{table}\n{END}{after}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--readme", action="store_true", help="write the table into README.md")
    args = parser.parse_args()
    with contextlib.redirect_stderr(sys.stderr):
        table = markdown(rows())
    print(table)
    if args.readme:
        write_readme(table)


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    main()
