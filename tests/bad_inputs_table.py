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


def with_pairs(count: int) -> str:
    rows = [f"rig01/wide/f0.png,{10 + 4 * k},{5 + 3 * k},rig02/wide/f0.png,{12 + 4 * k},{6 + 2 * k}"
            for k in range(count)]
    return "image_a,x_a,y_a,image_b,x_b,y_b\n" + "\n".join(rows) + "\n"


def rotate(data: dict, key: str, value) -> None:
    data["rigs"][1]["narrow_from_wide"][key] = value


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
    # --- images
    Case("the image folder misspelt", "nothing is written", lambda root: (inputs(root), ["run", "image", *RUN[2:]])[1]),
    Case("a folder under IMAGES that is not a rig of rigs.yaml", "nothing is written",
         with_images(lambda images: shutil.copytree(images / "rig02", images / "rig03"))),
    Case("a rig of rigs.yaml without its folder", "nothing is written",
         with_images(lambda images: shutil.rmtree(images / "rig02"))),
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
    Case("images directly in IMAGES/ instead of IMAGES/<rig>/<sensor>/", "nothing is written",
         with_images(lambda images: shutil.copy(images / "rig01" / "wide" / "f0.png", images / "f0.png"))),
    Case("a rig without a narrow folder (a warning: the run goes on)", "the run goes on; its narrow camera gets no pose",
         with_images(lambda images: shutil.rmtree(images / "rig02" / "narrow")), warning="NO NARROW IMAGES"),
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
    Case("a misspelt key in scale.yaml (`camera_distances`)", "nothing is written",
         with_scale({"camera_distances": [{"a": "rig01/wide", "b": "rig02/wide", "meters": 12.0}]})),
    # --- matches.csv
    Case("matches.csv saved by a spreadsheet with `;` separators", "nothing is written",
         with_matches(with_pairs(8).replace(",", ";"))),
    Case("matches.csv in Latin-1 with an accented file name", "nothing is written",
         with_matches(with_pairs(8).replace("f0.png", "fé.png").encode("latin-1"))),
    Case("matches.csv naming an image that does not exist", "nothing is written",
         with_matches(with_pairs(8).replace("rig02/wide/f0.png", "rig02/wide/f0.jpg"))),
    Case("matches.csv with 5 correspondences for a pair", "nothing is written", with_matches(with_pairs(5))),
    # --- frame offsets
    Case("`--frame-offsets` naming a rig that is not in rigs.yaml", "nothing is written",
         with_offsets("rig09: 1\n")),
    Case("`--frame-offsets` with half a frame (`rig02: 0.5`)", "nothing is written", with_offsets("rig02: 0.5\n")),
    Case("`--frame-offsets` beyond the recording (3 frames off, one frame recorded)", "nothing is written",
         with_offsets("rig02: 3\n")),
    # --- options
    Case("`--max-ratio 0`", "nothing is written", lambda root: (inputs(root), [*RUN, "--max-ratio", "0"])[1]),
    Case("`--max-ratio nan`", "nothing is written", lambda root: (inputs(root), [*RUN, "--max-ratio", "nan"])[1]),
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
    Case("`rigsfm report` on a folder without a result", "nothing is written",
         lambda root: (inputs(root), ["report", "images"])[1]),
    Case("a truncated `sparse/images.bin`", "nothing is written",
         on_workspace(lambda out: (out / "sparse" / "images.bin").write_bytes(
             (out / "sparse" / "images.bin").read_bytes()[:30]), ["report", "out"])),
    Case("a damaged `narrow_poses.json`", "nothing is written",
         on_workspace(lambda out: (out / "narrow_poses.json").write_text('{"narrow": ['), ["report", "out"])),
    Case("`rigsfm view` on a machine without a display", "nothing is written",
         on_workspace(lambda out: None, ["view", "out"])),
    Case("`rigsfm pick --port` a port already in use", "the CSV is untouched", port_in_use),
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
    usage = [line.strip("│ ").strip() for line in lines if "Invalid value" in line]
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
