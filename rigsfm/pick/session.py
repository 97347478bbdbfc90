"""The picker's state: two wide images, their picked pairs, and the CSV they are saved to on every change.

Only the rows of this image pair are edited; rows of other pairs in the same CSV are kept as they are. The page
removes one pair per click (undo, delete); a save that drops more than one of the saved pairs at once (a page that
lost its state, a second tab, a script sending ``{"pairs": []}``) first copies the CSV to ``<CSV>.bak``, so what
it replaced can be restored.
Image names are the workspace names ``<rig>/wide/<file>`` taken from the last three path components
(``IMAGES/<rig>/wide/<file>``); with a calibration file the wide camera of ``<rig>`` is used.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core.image_files import read_image, refuse_turned_images
from rigsfm.core.io import write_bytes_atomic
from rigsfm.run.manual_matches import Correspondence, ManualMatchError, read_manual_matches, write_manual_matches
from rigsfm.pick.epipolar import MIN_PAIRS, EpipolarModel, fit_model
from rigsfm.core.rig import RigCalibration

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PickerImage:
    name: str
    path: Path
    width: int
    height: int
    camera: pycolmap.Camera | None = None


def picker_image(path: Path, rigs: list[RigCalibration] | None) -> PickerImage:
    path = Path(path)
    parts = path.resolve().parts
    name = "/".join(parts[-3:]) if len(parts) >= 3 else path.name
    camera = None
    if rigs is not None:
        if len(parts) < 3 or parts[-2] != "wide":
            raise ManualMatchError(f"{path}: with --rigs the image must be IMAGES/<rig>/wide/<file>")
        by_name = {rig.name: rig for rig in rigs}
        if parts[-3] not in by_name:
            raise ManualMatchError(
                f"{path}: rig {parts[-3]!r} is not in the calibration file; "
                f"rigs there: {', '.join(sorted(by_name))}"
            )
        camera = by_name[parts[-3]].wide
    # the clicks are saved as COLMAP pixels of the image as stored, which a browser would show turned
    refuse_turned_images([path], calibration=None if camera is None else (
        lambda _: (f"{parts[-3]}'s wide camera", camera.width, camera.height)))
    image = read_image(path, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ManualMatchError(f"{path}: cannot be read as an image; give a wide image file")
    height, width = image.shape[:2]
    if camera is not None and (camera.width, camera.height) != (width, height):
        raise ManualMatchError(
            f"{path} is {width}x{height} but {parts[-3]}'s wide camera is calibrated for "
            f"{camera.width}x{camera.height}"
        )
    return PickerImage(name, path, width, height, camera)


class PickerSession:
    """Thread-safe state behind the page; every change is written to the CSV atomically."""

    def __init__(self, image_a: PickerImage, image_b: PickerImage, csv_path: Path, flag_px: float = 4.0):
        if image_a.name == image_b.name:
            raise ManualMatchError(f"both images are {image_a.name}; give two different wide images")
        self.images = (image_a, image_b)
        self.csv_path = Path(csv_path)
        self.flag_px = flag_px
        self.lock = threading.Lock()
        self.pairs: list[list[float]] = []  # [x_a, y_a, x_b, y_b]
        self.others: list[Correspondence] = []
        self.model: EpipolarModel | None = None
        self.distances: np.ndarray = np.zeros(0)
        self.reload()

    def reload(self) -> None:
        """Read the CSV from disk (if it exists): this pair's rows are edited, the others kept."""
        rows = read_manual_matches(self.csv_path) if self.csv_path.exists() else []
        a, b = (image.name for image in self.images)
        pairs, others = [], []
        for row in rows:
            if (row.image_a, row.image_b) == (a, b):
                pairs.append([*row.xy_a, *row.xy_b])
            elif (row.image_a, row.image_b) == (b, a):
                pairs.append([*row.xy_b, *row.xy_a])
            else:
                others.append(row)
        with self.lock:
            self.pairs, self.others = pairs, others
            self._refit()

    def _refit(self) -> None:
        xy = np.asarray(self.pairs, np.float64).reshape(-1, 4)
        cams = (
            (self.images[0].camera, self.images[1].camera)
            if self.images[0].camera is not None
            else (None, None)
        )
        fitted = fit_model(xy[:, :2], xy[:, 2:], self.flag_px, *cams)
        self.model, self.distances = fitted if fitted is not None else (None, np.full(len(xy), np.nan))

    def _check(self, pairs) -> list[list[float]]:
        clean = []
        for i, pair in enumerate(pairs):
            if not isinstance(pair, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                     for v in pair):
                raise ManualMatchError(f"pair {i + 1}: expected [x_a, y_a, x_b, y_b], got {pair!r}")
            try:
                values = [float(v) for v in pair]
            except OverflowError:
                values = [math.inf]
            if len(values) != 4 or not np.all(np.isfinite(values)):
                raise ManualMatchError(f"pair {i + 1}: expected four finite numbers")
            for (x, y), image in zip((values[:2], values[2:]), self.images):
                if not (0 <= x <= image.width and 0 <= y <= image.height):
                    raise ManualMatchError(f"pair {i + 1}: ({x:g}, {y:g}) lies outside {image.name}")
            clean.append(values)
        return clean

    @property
    def backup_path(self) -> Path:
        return self.csv_path.with_name(self.csv_path.name + ".bak")

    def set_pairs(self, pairs) -> dict:
        """Replace this image pair's correspondences and save the CSV (temporary file + rename); keep the CSV as it
        was in ``<CSV>.bak`` first when more than one saved pair would be lost (see the module docstring)."""
        if not isinstance(pairs, list):
            raise ManualMatchError("'pairs' must be a list of [x_a, y_a, x_b, y_b]")
        clean = self._check(pairs)
        a, b = (image.name for image in self.images)
        backup = None
        with self.lock:
            kept = {tuple(round(v, 3) for v in p) for p in clean}
            lost = [p for p in self.pairs if tuple(round(v, 3) for v in p) not in kept]
            if len(lost) > 1 and self.csv_path.is_file():
                backup = write_bytes_atomic(self.backup_path, self.csv_path.read_bytes())
                logger.warning("This save drops %d of the %d saved pairs of %s <-> %s: the CSV as it was is kept in %s",
                               len(lost), len(self.pairs), a, b, backup)
            self.pairs = clean
            rows = self.others + [Correspondence(a, (p[0], p[1]), b, (p[2], p[3])) for p in clean]
            write_manual_matches(self.csv_path, rows)
            self._refit()
        logger.info("Saved %d pairs to %s", len(clean), self.csv_path)
        state = self.state()
        if backup is not None:
            state["backup"] = str(backup)
        return state

    def state(self) -> dict:
        with self.lock:
            return {
                "images": [{"name": i.name, "width": i.width, "height": i.height} for i in self.images],
                "csv": str(self.csv_path),
                "calibrated": self.images[0].camera is not None,
                "min_pairs": MIN_PAIRS,
                "flag_px": self.flag_px,
                "model": self.model is not None,
                "pairs": [
                    {
                        "a": p[:2],
                        "b": p[2:],
                        "distance_px": None if np.isnan(d) else round(float(d), 2),
                        "flagged": bool(d > self.flag_px),
                    }
                    for p, d in zip(self.pairs, self.distances)
                ],
            }

    def epipolar(self, side: str, x: float, y: float) -> list | None:
        """Polyline in the other image of the epipolar line of (x, y) in ``side`` ('a' or 'b')."""
        with self.lock:
            if self.model is None:
                return None
            other = self.images[1] if side == "a" else self.images[0]
            return self.model.line((x, y), side, other.width, other.height)
