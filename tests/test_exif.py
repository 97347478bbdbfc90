"""EXIF Orientation: one decision for every reader. rigsfm works on the pixels as stored, as COLMAP's feature
extractor does, so every OpenCV read ignores the tag; an image whose tag turns or mirrors it for viewers is refused
where it enters (run with SIFT or ASIFT, calibrate, track, pick) with the files and the fix, and the report and the
picker's page show the stored pixels. The tagged files are real: an APP1 Exif segment (JPEG) or an eXIf chunk (PNG)
added to OpenCV's encoding, which OpenCV itself then turns on a default read."""

import re
import shutil
import struct
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import yaml
from bad_inputs_table import RUN, Case, inputs, run_case
from support import REAL_STEREO, exif_block, tag_orientation, write_tagged

from rigsfm.calibrate.options import CalibrateOptions
from rigsfm.calibrate.pipeline import calibrate
from rigsfm.core.errors import InputError
from rigsfm.core.image_files import decode_image, exif_orientation, read_image

REPO = Path(__file__).resolve().parents[1]
CHESS = {"type": "chessboard", "inner_corners": [9, 6], "square": 0.025}


def pattern(height=48, width=64):
    """A picture that differs from every turn and mirror of itself."""
    image = np.zeros((height, width), np.uint8)
    image[: height // 3, : width // 4] = 255
    image[height // 2:, width // 2: width // 2 + 5] = 128
    return image


# --- reading the tag ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("suffix", [".jpg", ".png"])
@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("orientation", range(1, 9))
def test_the_tag_is_read_as_opencv_applies_it(tmp_path, suffix, big_endian, orientation):
    ok, data = cv2.imencode(suffix, pattern())
    tagged = tag_orientation(data.tobytes(), orientation, big_endian)
    path = tmp_path / f"image{suffix}"
    path.write_bytes(tagged)
    assert exif_orientation(path) == exif_orientation(tagged) == orientation
    stored = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    turned_by_opencv = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)  # what the readers used to see
    assert (turned_by_opencv.shape != stored.shape or (turned_by_opencv != stored).any()) == (orientation != 1)
    for pixels in (read_image(path, cv2.IMREAD_GRAYSCALE), decode_image(tagged, cv2.IMREAD_GRAYSCALE)):
        assert np.array_equal(pixels, stored)
    assert np.array_equal(read_image(path, cv2.IMREAD_COLOR)[..., 0], stored)
    bitmap = pycolmap.Bitmap.read(path, as_rgb=False)  # COLMAP's own reader: the stored pixels
    assert (bitmap.width, bitmap.height) == (stored.shape[1], stored.shape[0])


def _tiff(pixels: np.ndarray, orientation: int) -> bytes:
    """An uncompressed 8-bit grey TIFF with an Orientation tag in IFD0."""
    height, width = pixels.shape
    entries = [(256, 3, width), (257, 3, height), (258, 3, 8), (259, 3, 1), (262, 3, 1), (273, 4, 0),
               (274, 3, orientation), (277, 3, 1), (278, 3, height), (279, 4, width * height)]
    start = 8 + 2 + 12 * len(entries) + 4
    table = b"".join(struct.pack("<HHI", tag, kind, 1) + (struct.pack("<HH", value, 0) if kind == 3 else
                     struct.pack("<I", start if tag == 273 else value)) for tag, kind, value in entries)
    return b"II" + struct.pack("<HIH", 42, 8, len(entries)) + table + struct.pack("<I", 0) + pixels.tobytes()


def test_tiff_webp_and_odd_files():
    # TIFF: OpenCV turns some orientations whatever the flags and cannot read others, COLMAP reads them as stored
    assert exif_orientation(_tiff(pattern(), 6)) == 6 and exif_orientation(_tiff(pattern(), 1)) == 1
    ok, webp = cv2.imencode(".webp", pattern())
    chunk = b"EXIF" + struct.pack("<I", len(exif_block(8))) + exif_block(8)
    riff = webp.tobytes() + chunk
    assert exif_orientation(riff[:4] + struct.pack("<I", len(riff) - 8) + riff[8:]) == 8
    ok, jpeg = cv2.imencode(".jpg", pattern())
    jpeg = jpeg.tobytes()
    xmp = b"http://ns.adobe.com/xap/1.0/\x00<x:xmpmeta/>"
    with_xmp = jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(xmp) + 2) + xmp + tag_orientation(jpeg, 3)[2:]
    assert exif_orientation(with_xmp) == 3  # the Exif segment after an XMP one
    assert exif_orientation(jpeg) is None and exif_orientation(cv2.imencode(".png", pattern())[1].tobytes()) is None
    assert exif_orientation(cv2.imencode(".bmp", pattern())[1].tobytes()) is None
    tagged = tag_orientation(jpeg, 6)
    for damaged in (tagged[:30], jpeg[:2] + b"\xff\xe1\x00\x10Exif\x00\x00MM\x00*\xff\xff\xff\xff" + jpeg[2:], b"", b"\xff\xd8\xff"):
        assert exif_orientation(damaged) is None  # left to the decoder's own check
    assert exif_orientation(Path("/nonexistent/image.jpg")) is None


def test_every_opencv_read_of_rigsfm_goes_through_the_one_reader():
    """OpenCV's default read turns the pixels: only rigsfm.core.image_files may call it, with the flag."""
    calls = re.compile(r"cv2\.(imread|imdecode|imreadmulti|imreadWithMetadata)\b")
    offenders = [f"{path.relative_to(REPO)}:{n}" for folder in ("rigsfm", "benchmarks")
                 for path in sorted((REPO / folder).rglob("*.py")) if path.name != "image_files.py"
                 for n, line in enumerate(path.read_text().splitlines(), 1) if calls.search(line)]
    assert offenders == []


# --- refused where the images enter --------------------------------------------------------------------------------

def tagged_inputs(root: Path, orientation: int = 6, calibrated: tuple[int, int] = (64, 48), which=None) -> None:
    """bad_inputs_table's small inputs, the images as JPEGs tagged ``orientation`` (only ``which`` if given)."""
    inputs(root)
    for path in sorted((root / "images").rglob("*.png")):
        pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        path.unlink()
        name = str(path.relative_to(root / "images").with_suffix(".jpg"))
        if which is None or name in which:
            write_tagged(path.with_suffix(".jpg"), pixels, orientation)
        else:
            cv2.imwrite(str(path.with_suffix(".jpg")), pixels)
    rigs = yaml.safe_load((root / "rigs.yaml").read_text())
    for rig in rigs["rigs"]:
        for camera in rig["sensors"].values():
            camera.update(width=calibrated[0], height=calibrated[1], params=[50.0, 50.0, calibrated[0] / 2,
                                                                              calibrated[1] / 2])
    (root / "rigs.yaml").write_text(yaml.safe_dump(rigs, sort_keys=False))


@pytest.mark.parametrize("features", ["sift", "asift"])
def test_run_refuses_tagged_images_whose_stored_pixels_match_the_calibration(tmp_path, features):
    case = Case("", "", lambda root: (tagged_inputs(root), [*RUN, "--features", features, "--world", "mapping"])[1])
    code, message = run_case(case, tmp_path / "case")
    assert code == 1, message
    assert message == (
        "error: 'images/rig01/wide/f0.jpg' and 3 more ('images/rig01/narrow/f0.jpg', 'images/rig02/wide/f0.jpg', ...) "
        "carry the EXIF tag Orientation=6 (viewers show them turned 90° clockwise), but rigsfm, like COLMAP, works "
        "on the pixels as stored; the stored 64x48 pixels are what the wide camera of rig 'rig01' is calibrated for: "
        "remove the tag and keep the pixels (`exiftool -Orientation=1 -n -overwrite_original -r images`)")
    assert not (tmp_path / "case" / "out").exists()


def test_run_refuses_images_whose_calibration_was_made_on_the_turned_pixels(tmp_path):
    """The old `rigsfm calibrate` read tagged images turned: its rigs.yaml is 48x64 for 64x48 stored pixels."""
    case = Case("", "", lambda root: (tagged_inputs(root, calibrated=(48, 64), which={"rig02/wide/f0.jpg"}),
                                      RUN)[1])
    code, message = run_case(case, tmp_path / "case")
    assert code == 1
    assert message == (
        "error: 'images/rig02/wide/f0.jpg' carries the EXIF tag Orientation=6 (viewers show it turned 90° clockwise), "
        "but rigsfm, like COLMAP, works on the pixels as stored; the wide camera of rig 'rig02' is calibrated for the image "
        "as shown (48x64), not as stored (64x48): turn the pixels as the tag says (`mogrify -auto-orient images/rig02/wide/f0.jpg`, "
        "or `exiftran -ai images/rig02/wide/f0.jpg` for JPEG without loss)")


def test_run_names_both_fixes_when_the_size_cannot_tell(tmp_path):
    case = Case("", "", lambda root: (tagged_inputs(root, orientation=3, which={"rig01/wide/f0.jpg"}), RUN)[1])
    code, message = run_case(case, tmp_path / "case")
    assert code == 1
    assert message.endswith(
        "(viewers show it turned 180°), but rigsfm, like COLMAP, works on the pixels as stored; remove the tag "
        "(`exiftool -Orientation=1 -n -overwrite_original images/rig01/wide/f0.jpg`) if the wide camera of rig 'rig01' was "
        "calibrated on "
        "the pixels as stored, or turn the pixels as the tag says (`mogrify -auto-orient images/rig01/wide/f0.jpg`, "
        "or `exiftran -ai images/rig01/wide/f0.jpg` for JPEG without loss) if it was calibrated on the images as "
        "shown")


def test_untagged_and_upright_tagged_images_are_accepted(tmp_path):
    from rigsfm.run.pipeline import load_inputs

    tagged_inputs(tmp_path, orientation=1)
    assert len(load_inputs(tmp_path / "images", tmp_path / "rigs.yaml").images) == 4


def test_calibrate_refuses_tagged_board_images(tmp_path):
    """OpenCV's real stereo boards (640x480 JPEGs) tagged as a camera on its side writes them: the old code
    calibrated the turned 480x640 pixels, a calibration `rigsfm run` then refused for the same files."""
    for sensor, side in (("wide", "left"), ("narrow", "right")):
        folder = tmp_path / "BOARD" / "rig01" / sensor
        folder.mkdir(parents=True)
        for n in ("01", "02", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"):
            data = (REAL_STEREO / f"{side}{n}.jpg").read_bytes()
            (folder / f"{n}.jpg").write_bytes(tag_orientation(data, 6))
    (tmp_path / "board.yaml").write_text(yaml.safe_dump(CHESS))
    with pytest.raises(InputError) as error:
        calibrate(tmp_path / "BOARD", tmp_path / "out" / "rigs.yaml", CalibrateOptions(board=tmp_path / "board.yaml"))
    board = tmp_path / "BOARD"
    assert str(error.value) == (
        f"'{board}/rig01/wide/01.jpg' and 25 more ('{board}/rig01/wide/02.jpg', '{board}/rig01/wide/03.jpg', ...) carry "
        "the EXIF tag Orientation=6 (viewers show them turned 90° clockwise), but rigsfm, like COLMAP, works on the "
        f"pixels as stored; remove the tag (`exiftool -Orientation=1 -n -overwrite_original -r {board}`) or turn "
        f"the pixels as the tag says (`mogrify -auto-orient {board}/*/*/*.jpg`, or `exiftran -ai {board}/*/*/*.jpg` for "
        "JPEG without loss); "
        "give the images of `rigsfm run` the same treatment, so that the calibration and the run see the same pixels")
    assert not (tmp_path / "out").exists()


def test_pick_refuses_a_tagged_image_and_serves_stored_pixels(tmp_path):
    from rigsfm.core.rig import load_rigs
    from rigsfm.pick.server import _image_bytes
    from rigsfm.pick.session import picker_image

    tagged_inputs(tmp_path, which={"rig01/wide/f0.jpg"})
    rigs = load_rigs(tmp_path / "rigs.yaml")
    tagged, plain = tmp_path / "images/rig01/wide/f0.jpg", tmp_path / "images/rig02/wide/f0.jpg"
    with pytest.raises(InputError, match=r"rig01/wide/f0.jpg' carries the EXIF tag Orientation=6 .* the stored "
                                         r"64x48 pixels are what the wide camera of rig 'rig01' is calibrated for: remove the tag"):
        picker_image(tagged, rigs)
    with pytest.raises(InputError, match=rf"f0.jpg' carries the EXIF tag Orientation=6 .*; remove the tag \(`exiftool "
                                         rf"-Orientation=1 -n -overwrite_original {re.escape(str(tagged))}`\) or turn "
                                         rf"the pixels as the tag says \(`mogrify -auto-orient {re.escape(str(tagged))}`"):
        picker_image(tagged, None)
    assert picker_image(plain, rigs).width == 64
    # a browser turns a tagged JPEG: the page gets a PNG of the stored pixels instead (an untagged file as it is)
    body, kind = _image_bytes(tagged)
    assert kind == "image/png"
    assert np.array_equal(cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_UNCHANGED),
                          cv2.imread(str(tagged), cv2.IMREAD_UNCHANGED))
    assert _image_bytes(plain) == (plain.read_bytes(), "image/jpeg")


# --- a finished run: track, the report, the self-check and floor matching on tagged copies -----------------------

@pytest.fixture(scope="module")
def tagged_copy(three_rig_run, tmp_path_factory):
    """The 3-rig run's images as PNGs carrying Orientation=3 (turned 180°: the sizes stay, so only the pixels
    tell), byte for byte the same pixels."""
    dataset, out, _ = three_rig_run
    root = tmp_path_factory.mktemp("tagged") / "images"
    for path in sorted(dataset.images.rglob("*.png")):
        target = root / path.relative_to(dataset.images)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(tag_orientation(path.read_bytes(), 3))
    return dataset, out, root


@pytest.mark.slow
def test_track_refuses_tagged_frames(tagged_copy, tmp_path):
    from rigsfm.track.pipeline import track
    from rigsfm.track.register import read_grey

    dataset, out, images = tagged_copy
    work = tmp_path / "out"
    shutil.copytree(out, work)
    frame = tmp_path / "new"
    for path in sorted(images.glob("rig0*/*/*.png")):
        target = frame / path.relative_to(images)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    with pytest.raises(InputError, match=rf"^'{re.escape(str(frame))}/rig01/wide/\S+' and \d+ more .* carry the "
                                         r"EXIF tag Orientation=3 \(viewers show them turned 180°\).* remove the tag "
                                         rf"\(`exiftool -Orientation=1 -n -overwrite_original -r {re.escape(str(frame))}`"):
        track(work, frame)
    assert not (work / "track").exists() or not any((work / "track").iterdir())
    one = next(iter(sorted(images.rglob("*.png"))))
    stored = cv2.imread(str(dataset.images / one.relative_to(images)), cv2.IMREAD_GRAYSCALE)
    assert np.array_equal(read_grey(one), stored) and np.array_equal(read_grey(one.read_bytes()), stored)


@pytest.mark.slow
def test_report_self_check_and_floor_matching_read_the_stored_pixels(tagged_copy):
    from rigsfm.inspect.report.html import epipolar_section
    from rigsfm.inspect.report.write import load_result
    from rigsfm.run.checks.guided import load_narrow
    from rigsfm.run.world.floor_matching import load_floor_images

    dataset, out, images = tagged_copy
    reconstruction, narrow, summary = load_result(out)
    sections = []
    for folder in (dataset.images, images):
        summary.inputs.images = str(folder)
        sections.append(epipolar_section(out, summary, reconstruction, narrow))
    assert "<figure>" in sections[0] and sections[1] == sections[0]  # the same figures, drawn on the same pixels
    image = next(im for im in reconstruction.images.values() if im.has_pose and "/narrow/" in im.name)
    loaded = load_narrow(image, images, None, 1000)  # the self-check's reader: None meant "cannot read as a WxH image"
    assert loaded is not None and np.array_equal(loaded.gray, read_image(dataset.images / image.name, 0))
    floor = load_floor_images(reconstruction, images)
    assert len(floor) and [len(f.xy) for f in floor] == [len(f.xy) for f in load_floor_images(reconstruction,
                                                                                              dataset.images)]
