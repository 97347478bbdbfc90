"""Finding rigs and synchronised frames: ``ROOT/<rig>/wide/*`` and ``ROOT/<rig>/narrow/*``.

Frames are paired by file name without extension (same name = same instant). ``ROOT/wide`` +
``ROOT/narrow`` directly (no rig folder) is accepted as a single rig named after ROOT.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2

from rigsfm.core.errors import InputError
from rigsfm.core.image_files import read_image, refuse_turned_images

IMAGE_EXTENSIONS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp"}
SENSORS = ("wide", "narrow")


@dataclass
class RigFrames:
    name: str
    wide: dict[str, Path]  # frame name -> image
    narrow: dict[str, Path]

    @property
    def frames(self) -> list[str]:
        return sorted(self.wide)


def _images(folder: Path) -> dict[str, Path]:
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    out: dict[str, Path] = {}
    for p in files:
        if p.stem in out:
            raise InputError(f"{folder}: two images share the frame name {p.stem!r} ({out[p.stem].name}, {p.name})")
        out[p.stem] = p
    return out


def _rig(folder: Path, name: str, what: str) -> RigFrames:
    sides = {}
    for sensor in SENSORS:
        sub = folder / sensor
        if not sub.is_dir():
            raise InputError(f"{what}: rig folder {folder} has no '{sensor}' subfolder (expected {folder}/wide and "
                             f"{folder}/narrow with synchronised images of the same names)")
        sides[sensor] = _images(sub)
        if not sides[sensor]:
            raise InputError(f"{what}: {sub} contains no images ({', '.join(sorted(IMAGE_EXTENSIONS))})")
    only_w = sorted(set(sides["wide"]) - set(sides["narrow"]))
    only_n = sorted(set(sides["narrow"]) - set(sides["wide"]))
    if only_w or only_n:
        parts = []
        if only_w:
            parts.append(f"only in wide: {', '.join(only_w[:5])}{' ...' if len(only_w) > 5 else ''}")
        if only_n:
            parts.append(f"only in narrow: {', '.join(only_n[:5])}{' ...' if len(only_n) > 5 else ''}")
        raise InputError(f"{what}: rig '{name}': wide and narrow frame names do not match ({'; '.join(parts)}); "
                         "synchronised images must have the same file name in both folders - rename or remove them")
    return RigFrames(name=name, wide=sides["wide"], narrow=sides["narrow"])


def discover_rigs(root: Path, what: str = "board images") -> list[RigFrames]:
    root = Path(root)
    if root.exists() and not root.is_dir():
        raise InputError(f"{what}: {root} is a file, not a folder; give the folder that holds <rig>/wide and "
                         "<rig>/narrow")
    if not root.is_dir():
        raise InputError(f"{what} folder {root} does not exist")
    if (root / "wide").is_dir() or (root / "narrow").is_dir():
        rigs = [_rig(root, root.resolve().name, what)]
    else:
        folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
        if not folders:
            raise InputError(f"{what}: {root} has no rig folders; expected {root}/<rig>/wide and {root}/<rig>/narrow")
        rigs = [_rig(p, p.name, what) for p in folders]
    # the calibration is made in the pixels as stored, which `rigsfm run` and COLMAP use: a tag that turns them
    # for viewers is refused here rather than calibrated in one frame and run in another
    refuse_turned_images([path for rig in rigs for side in (rig.wide, rig.narrow) for path in side.values()],
                         folder=root, then="; give the images of `rigsfm run` the same treatment, so that the "
                         "calibration and the run see the same pixels")
    return rigs


def image_size(path: Path) -> tuple[int, int]:
    image = read_image(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"cannot read image {path}; is it a valid image file?")
    return int(image.shape[1]), int(image.shape[0])
