"""The image folder contract: ``IMAGES/<rig>/<sensor>/<frame file>``, validated against rigs.yaml.

Files with the same name under one rig are one synchronised frame. Every frame needs its wide image;
the narrow image is optional. Image names inside the workspace are ``<rig>/<sensor>/<frame file>``.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2

from rigsfm.core.errors import InputError
from rigsfm.core.image_files import read_image, refuse_turned_images
from rigsfm.core.names import SENSORS, ImageName, Sensor
from rigsfm.core.rig import RigCalibration

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


def scan_images(image_dir: Path, rigs: Sequence[RigCalibration], *, check_pixels: bool = True) -> list[ImageEntry]:
    """List and validate every image under ``image_dir``.

    Checks: the folder layout, that every folder is a rig in rigs.yaml and every rig has wide images,
    that every narrow image has its wide partner, that no image carries an EXIF Orientation that turns it
    (:func:`~rigsfm.core.image_files.refuse_turned_images`), and (``check_pixels``) that each image decodes
    and has the size its camera is calibrated for.
    """
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise InputError(f"image folder {image_dir} does not exist")
    rig_by_name = {rig.name: rig for rig in rigs}
    folders = sorted(p for p in image_dir.iterdir() if not _is_hidden(p))
    stray = [p.name for p in folders if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    if stray:
        raise InputError(
            f"{image_dir}: images must sit in <rig>/<sensor>/ folders, found {stray[0]} at the top level"
        )
    unknown = [p.name for p in folders if p.is_dir() and p.name not in rig_by_name]
    if unknown:
        raise InputError(
            f"{image_dir}: folder(s) {', '.join(unknown)} have no rig in the calibration file; "
            "add them to rigs.yaml or move them out of the image folder"
        )
    entries: list[ImageEntry] = []
    for rig in rigs:
        rig_dir = image_dir / rig.name
        if not rig_dir.is_dir():
            raise InputError(f"rig {rig.name} from the calibration file has no folder {rig_dir}")
        extra = [p.name for p in rig_dir.iterdir() if not _is_hidden(p) and p.name not in SENSORS]
        if extra:
            raise InputError(f"{rig_dir}: unexpected {', '.join(sorted(extra))}; only 'wide' and 'narrow' belong here")
        frames: dict[str, set[str]] = {}
        for sensor in SENSORS:
            sensor_dir = rig_dir / sensor
            if not sensor_dir.is_dir():
                continue
            for path in sorted(sensor_dir.iterdir()):
                if _is_hidden(path):
                    continue
                if path.is_dir():
                    raise InputError(f"{path}: sub-folders are not allowed below {sensor_dir}")
                if path.suffix.lower() not in IMAGE_SUFFIXES:
                    logger.warning("Ignoring %s: not an image file", path)
                    continue
                frames.setdefault(sensor, set()).add(path.name)
                entries.append(ImageEntry(rig.name, sensor, path.name, path))
        wide, narrow = frames.get("wide", set()), frames.get("narrow", set())
        if not wide:
            raise InputError(f"rig {rig.name} has no wide images in {rig_dir / 'wide'}")
        orphans = sorted(narrow - wide)
        if orphans:
            raise InputError(
                f"{rig_dir / 'narrow' / orphans[0]} has no wide image of the same name in {rig_dir / 'wide'}: "
                "every frame is registered through its wide image; add it or remove the narrow one"
            )
    by_path = {entry.path: entry for entry in entries}

    def calibration(path: Path) -> tuple[str, int, int]:
        entry = by_path[path]
        camera = rig_by_name[entry.rig].camera(entry.sensor)
        return f"rig {entry.rig}'s {entry.sensor} camera", camera.width, camera.height

    # before the sizes: a calibration of the turned images would otherwise read as a wrong resolution
    refuse_turned_images([entry.path for entry in entries], folder=image_dir, calibration=calibration)
    if check_pixels:
        for entry in entries:
            check_image(entry, rig_by_name[entry.rig].camera(entry.sensor))
    return entries


def rigs_without_narrow(image_dir: Path, images: Sequence[ImageEntry], rigs: Sequence[RigCalibration]) -> list[str]:
    """One line per rig with no narrow image (allowed: its wide images still register, its narrow camera gets no
    pose); for a warning, since a misnamed or forgotten narrow folder otherwise goes unnoticed."""
    with_narrow = {e.rig for e in images if e.sensor == "narrow"}
    return [f"rig {rig.name} has no narrow images ({Path(image_dir) / rig.name / 'narrow'} "
            f"{'is empty' if (Path(image_dir) / rig.name / 'narrow').is_dir() else 'does not exist'}): its narrow "
            "camera gets no pose" for rig in rigs if rig.name not in with_narrow]


def check_image(entry: ImageEntry, camera) -> None:
    """The image decodes and matches its camera's calibrated size."""
    image = read_image(entry.path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{entry.path}: cannot be read as an image (corrupt or unsupported); replace it")
    height, width = image.shape[:2]
    if (width, height) != (camera.width, camera.height):
        raise InputError(
            f"{entry.path} is {width}x{height} but rig {entry.rig}'s {entry.sensor} camera is calibrated for "
            f"{camera.width}x{camera.height}; use the calibration of this camera at this resolution"
        )
