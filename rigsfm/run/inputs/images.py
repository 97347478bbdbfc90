"""Stage 1, validate: the image folder contract: ``IMAGES/<rig>/<sensor>/<frame file>``, validated against rigs.yaml.

Files with the same name under one rig are one synchronised frame. Every frame needs its wide image;
the narrow image is optional. Image names inside the workspace are ``<rig>/<sensor>/<frame file>``, spelled as on
disk; a rig folder matches its rigs.yaml name Unicode-normalised (NFC: macOS writes names decomposed), and
:func:`with_folder_names` gives each rig its folder's spelling so that every name reads its file. What sits where
an image should but is no regular file (a FIFO, which would block the read forever, a device, a socket, a folder
named like an image, a broken link) is refused with one line.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2

from rigsfm.core.errors import InputError
from rigsfm.core.image_files import read_image, refuse_turned_images, stored_size
from rigsfm.core.io import access_problem, file_kind, stat_input
from rigsfm.core.names import SENSORS, ImageName, Sensor, quoted
from rigsfm.core.rig import RigCalibration, nfc

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm"}


@dataclass(frozen=True)
class ImageEntry:
    """One image file: which rig and sensor it belongs to and which frame it is."""

    rig: str
    sensor: Sensor
    frame: str
    path: Path

    @property
    def image_name(self) -> ImageName:
        return ImageName(self.rig, self.sensor, self.frame)

    @property
    def name(self) -> str:
        """The image's name in the workspace and its models, ``<rig>/<sensor>/<frame file>``."""
        return str(self.image_name)


def _is_hidden(path: Path) -> bool:
    return path.name.startswith(".")


def check_image_folder(image_dir: Path) -> Path:
    """``image_dir`` is a folder rigsfm can list; an ``InputError`` with the true cause and the fix otherwise."""
    image_dir = Path(image_dir)
    _, kind = stat_input(image_dir, "image folder")
    if kind != "a folder":
        raise InputError(f"image folder '{image_dir}' is {kind or 'a file'}, not a folder; give the folder that holds "
                         "<rig>/<sensor>/<frame file>")
    _listing(image_dir)
    return image_dir


def _listing(folder: Path) -> list[Path]:
    """The entries of ``folder``; an unreadable one is refused with its cause (never taken for an empty one)."""
    try:
        return sorted(folder.iterdir())
    except OSError as error:
        raise InputError(f"folder '{folder}' {access_problem(folder, error)}") from None


def _problem(path: Path, what: str) -> str | None:
    """Why ``path`` (following links) is no regular file or folder, in words after the path, ending with the fix
    for ``what`` it should be; None when it is one."""
    try:
        mode = os.stat(path).st_mode
    except OSError as error:
        return access_problem(path, error)
    kind = file_kind(mode)
    if kind in (None, "a folder"):
        return None
    return f"is {kind}, not {what}; replace it with {what} or move it out of the image folder"


def rig_folders(image_dir: Path) -> dict[str, Path]:
    """The rig folders under ``image_dir`` by their NFC name; two folders whose names are equal in NFC are
    refused (the same rig twice, spelled two ways)."""
    folders: dict[str, Path] = {}
    for path in _listing(Path(image_dir)):
        if _is_hidden(path) or not path.is_dir():
            continue
        key = nfc(path.name)
        if key in folders:
            raise InputError(f"{image_dir}: folders {folders[key].name!r} and {path.name!r} are the same name in two "
                             "Unicode spellings (composed and decomposed); merge them into one")
        folders[key] = path
    return folders


def with_folder_names(image_dir: Path, rigs: Sequence[RigCalibration]) -> list[RigCalibration]:
    """``rigs`` each named as its folder under ``image_dir`` is spelled on disk where the two differ only in their
    Unicode form (a decomposed macOS folder, a composed rigs.yaml): image names then read their files."""
    folders = rig_folders(image_dir)
    out = []
    for rig in rigs:
        folder = folders.get(nfc(rig.name))
        out.append(rig if folder is None or folder.name == rig.name else replace(rig, name=folder.name))
    return out


def scan_images(image_dir: Path, rigs: Sequence[RigCalibration], *, check_pixels: bool = True) -> list[ImageEntry]:
    """List and validate every image under ``image_dir``.

    Checks: the folder layout, that every folder is a rig in rigs.yaml and every rig has wide images,
    that every narrow image has its wide partner, that no image carries an EXIF Orientation that turns it
    (:func:`~rigsfm.core.image_files.refuse_turned_images`), and (``check_pixels``) that each image decodes
    and has the size its camera is calibrated for.
    """
    image_dir = check_image_folder(image_dir)
    rig_by_name = {rig.name: rig for rig in rigs}
    known = {nfc(rig.name) for rig in rigs}
    folders = [p for p in _listing(image_dir) if not _is_hidden(p)]
    stray = [p.name for p in folders if not p.is_dir() and p.suffix.lower() in IMAGE_SUFFIXES]
    if stray:
        raise InputError(
            f"{image_dir}: images must sit in <rig>/<sensor>/ folders, found '{stray[0]}' at the top level"
        )
    by_name = rig_folders(image_dir)
    unknown = [path.name for key, path in by_name.items() if key not in known]
    if unknown:
        raise InputError(
            f"{image_dir}: folder(s) {quoted(unknown)} have no rig in the calibration file; "
            "add them to rigs.yaml or move them out of the image folder"
        )
    entries: list[ImageEntry] = []
    for rig in rigs:
        rig_dir = by_name.get(nfc(rig.name))
        if rig_dir is None:
            raise InputError(f"rig '{rig.name}' from the calibration file has no folder '{image_dir / rig.name}': put its "
                             f"images in {image_dir / rig.name}/wide/ and narrow/, or leave it out of a copy of "
                             "rigs.yaml for this run")
        extra = [p.name for p in _listing(rig_dir) if not _is_hidden(p) and p.name not in SENSORS]
        if extra:
            raise InputError(f"{rig_dir}: unexpected {quoted(sorted(extra))}; only 'wide' and 'narrow' belong here")
        frames: dict[str, set[str]] = {}
        for sensor in SENSORS:
            sensor_dir = rig_dir / sensor
            if not sensor_dir.is_dir():
                problem = _problem(sensor_dir, f"the folder of the rig's {sensor} images")
                if problem is not None and os.path.lexists(sensor_dir):
                    raise InputError(f"'{sensor_dir}' {problem}")
                continue
            for path in _listing(sensor_dir):
                if _is_hidden(path):
                    continue
                if path.is_dir():
                    raise InputError(f"{path}: sub-folders are not allowed below '{sensor_dir}'")
                if path.suffix.lower() not in IMAGE_SUFFIXES:
                    logger.warning("Ignoring '%s': not an image file", path)
                    continue
                problem = _problem(path, "an image file")
                if problem is not None:
                    raise InputError(f"'{path}' {problem}")
                frame = nfc(path.name)
                if frame in frames.get(sensor, set()):
                    raise InputError(f"{sensor_dir}: two files are named {path.name!r} in two Unicode spellings "
                                     "(composed and decomposed); keep one")
                frames.setdefault(sensor, set()).add(frame)
                entries.append(ImageEntry(rig.name, sensor, path.name, path))
        wide, narrow = frames.get("wide", set()), frames.get("narrow", set())
        if not wide:
            raise InputError(f"rig '{rig.name}' has no wide images in '{rig_dir / 'wide'}'")
        orphans = sorted(narrow - wide)
        if orphans:
            raise InputError(
                f"'{rig_dir / 'narrow' / orphans[0]}' has no wide image of the same name in '{rig_dir / 'wide'}': "
                "every frame is registered through its wide image; add it or remove the narrow one"
            )
    by_path = {entry.path: entry for entry in entries}

    def calibration(path: Path) -> tuple[str, int, int]:
        entry = by_path[path]
        camera = rig_by_name[entry.rig].camera(entry.sensor)
        return f"the {entry.sensor} camera of rig '{entry.rig}'", camera.width, camera.height

    # before the sizes: a calibration of the turned images would otherwise read as a wrong resolution
    refuse_turned_images([entry.path for entry in entries], folder=image_dir, calibration=calibration)
    if check_pixels:
        for entry in entries:
            check_image(entry, rig_by_name[entry.rig].camera(entry.sensor))
    return entries


def rigs_without_narrow(image_dir: Path, images: Sequence[ImageEntry], rigs: Sequence[RigCalibration]) -> list[str]:
    """One line per rig with no narrow image, or without one in some of its frames (allowed: its wide images still
    register, its narrow camera gets no pose there); for a warning, since a misnamed or forgotten narrow folder or
    file otherwise goes unnoticed."""
    frames: dict[tuple[str, str], set[str]] = {}
    for e in images:
        frames.setdefault((e.rig, e.sensor), set()).add(e.frame)
    lines = []
    for rig in rigs:
        narrow, wide = frames.get((rig.name, "narrow"), set()), frames.get((rig.name, "wide"), set())
        if not narrow:
            folder = Path(image_dir) / rig.name / "narrow"
            lines.append(f"rig '{rig.name}' has no narrow images ('{folder}' "
                         f"{'is empty' if folder.is_dir() else 'does not exist'}): its narrow camera gets no pose")
        elif wide - narrow:
            missing = sorted(wide - narrow)
            lines.append(f"rig '{rig.name}' has none in {len(missing)} of its {len(wide)} frames "
                         f"({quoted(missing[:3])}{' ...' if len(missing) > 3 else ''}): its narrow camera gets no pose "
                         "in them")
    return lines


def rigs_missing_frames(images: Sequence[ImageEntry], rigs: Sequence[RigCalibration], shown: int = 3) -> str | None:
    """One line naming each rig that lacks a whole frame (no wide image, hence no narrow one, of a name other rigs
    have) and the frames it lacks (``shown`` of them a rig), and each frame only a minority of rigs has with its rigs;
    None where every rig has every frame. For a warning: a file misnamed or lost in copying otherwise goes unnoticed,
    and that rig adds no view at that instant (no synchronised narrow pair with it there)."""
    frames: dict[str, set[str]] = {rig.name: set() for rig in rigs}
    for e in images:
        if e.sensor == "wide":
            frames[e.rig].add(e.frame)
    every = set().union(*frames.values())
    held = {frame: sorted(name for name, have in frames.items() if frame in have) for frame in every}
    # a frame a minority of rigs has is named with its holders: one rig's misnamed file, not the others' loss
    rare = sorted(frame for frame, holders in held.items() if 2 * len(holders) < len(rigs))
    missing = {name: sorted(every - have - set(rare)) for name, have in frames.items() if every - have - set(rare)}
    if not missing and not rare:
        return None
    items = [f"'{name}' lacks {quoted(lacks[:shown])}{' ...' if len(lacks) > shown else ''}"
             f"{f' ({len(lacks)} frames)' if len(lacks) > shown else ''}" for name, lacks in missing.items()]
    items += [f"{quoted([frame])} is only in {quoted(held[frame][:shown])}" for frame in rare[:shown]]
    items += [f"{len(rare) - shown} more frames only a few rigs have"] if len(rare) > shown else []
    head = (f"{len(missing)} of {len(rigs)} rigs lack frames other rigs have" if missing
            else f"{len(rare)} of {len(every)} frames are in only a few rigs")
    return (f"{head} ({'; '.join(items)}; {len(every)} frames in all): "
            "a rig adds no view at a frame it lacks; check for a file misnamed or not copied")


def unreadable_image(path: Path | str) -> str:
    """What `run` and `track` say of an image file that does not decode."""
    return f"{path}: cannot be read as an image (corrupt or unsupported); replace it"


def check_image(entry: ImageEntry, camera) -> None:
    """The image decodes and matches its camera's calibrated size."""
    try:
        with open(entry.path, "rb"):  # OpenCV reads a permission denial as a corrupt file
            pass
    except OSError as error:
        raise InputError(f"'{entry.path}' {access_problem(entry.path, error)}") from None
    image = read_image(entry.path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(unreadable_image(entry.path))
    _check_size(entry, camera, image.shape[1], image.shape[0])


def check_stored_size(entry: ImageEntry, camera) -> None:
    """:func:`check_image` from the file's header where it gives the size (PNG, JPEG: no pixels decoded, so
    cheap enough before any heavy work over a whole recording); the pixels are read where it does not."""
    size = stored_size(entry.path)
    if size is None:
        check_image(entry, camera)
    else:
        _check_size(entry, camera, *size)


def _check_size(entry: ImageEntry, camera, width: int, height: int) -> None:
    if (width, height) != (camera.width, camera.height):
        raise InputError(
            f"'{entry.path}' is {width}x{height} but the {entry.sensor} camera of rig '{entry.rig}' is calibrated for "
            f"{camera.width}x{camera.height}; use the calibration of this camera at this resolution"
        )
