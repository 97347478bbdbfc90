"""The picker's state: two wide images, their picked pairs, and the CSV they are saved to on every change.

Only the rows of this image pair are edited; rows of other pairs in the same CSV are kept as they are, read again
from the file at every save (another ``rigsfm pick`` may be writing them). Every state has a revision; the page
sends the one its pairs started from, and a save from a page that is behind (a second tab, a page left open) is
applied as its own additions and removals on top of the newer pairs, never in place of them. A save that still
drops more than one saved pair at once (a script sending ``{"pairs": []}``) first copies the CSV to a dated
``<CSV>.<YYYYmmdd-HHMMSS>.bak`` that no later save replaces. A save that cannot be written (the CSV's folder gone
or made a file, a full disk) changes nothing saved: the page says so, and the pairs it held are kept in a file
in the temporary folder, named in that message and when the picker stops.
Image names are the workspace names ``<rig>/wide/<file>`` taken from the last three path components
(``IMAGES/<rig>/wide/<file>``); with a calibration file the wide camera of ``<rig>`` is used.
"""

from __future__ import annotations

import logging
import math
import os
import secrets
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.image_files import read_image, refuse_turned_images
from rigsfm.core.io import write_bytes_atomic
from rigsfm.core.rig import RigCalibration
from rigsfm.core.workspace import os_error_text
from rigsfm.pick.epipolar import MIN_PAIRS, EpipolarModel, fit_model
from rigsfm.run.matching.manual_matches import (
    Correspondence,
    ManualMatchError,
    format_manual_matches,
    read_manual_matches,
    write_manual_matches,
)

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
    # the CSV names it <rig>/wide/<file>, all `rigsfm run --manual-matches` takes: refused now, not after the clicks
    if len(parts) < 3 or parts[-2] != "wide":
        raise ManualMatchError(f"{path}: the image must be a wide image, IMAGES/<rig>/wide/<file> (the CSV names it "
                               "<rig>/wide/<file>, as `rigsfm run --manual-matches` reads it)")
    if rigs is not None:
        by_name = {rig.name: rig for rig in rigs}
        if parts[-3] not in by_name:
            raise ManualMatchError(
                f"{path}: rig {parts[-3]!r} is not in the calibration file; "
                f"rigs there: {', '.join(sorted(by_name))}"
            )
        camera = by_name[parts[-3]].wide
    # the clicks are saved as COLMAP pixels of the image as stored, which a browser would show turned
    refuse_turned_images([path], calibration=None if camera is None else (
        lambda _: (f"the wide camera of rig '{parts[-3]}'", camera.width, camera.height)))
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


class StalePage(ManualMatchError):
    """A save from a page whose revision this picker never served (a page of an earlier ``rigsfm pick``)."""


class SaveFailed(WorkspaceError):
    """The CSV could not be written; nothing saved changed (``rescue`` holds the pairs that were to be saved)."""


def _key(pair) -> tuple[float, ...]:
    return tuple(round(v, 3) for v in pair)


def merge(current: list[list[float]], base: list[list[float]], page: list[list[float]]) -> list[list[float]]:
    """A page's edit of ``base`` (its additions and removals) applied to ``current``, the newer saved pairs."""
    if [_key(p) for p in base] == [_key(p) for p in current]:
        return page
    before, after = {_key(p) for p in base}, {_key(p) for p in page}
    removed, kept = before - after, [p for p in current if _key(p) not in before - after]
    have = {_key(p) for p in kept}
    added = [p for p in page if _key(p) not in before and _key(p) not in have and _key(p) not in removed]
    return kept + added


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
        self.token = secrets.token_hex(4)  # revisions of another picker process never match this one's
        self.revision = 0
        self.history: dict[int, list[list[float]]] = {}
        self.unsaved: list[list[float]] | None = None  # the pairs of the last save that could not be written
        self.save_error = ""
        self.rescue: Path | None = None
        self.reload()

    def _read(self) -> tuple[list[list[float]], list[Correspondence]]:
        """This pair's rows and the others, as the CSV on disk holds them now."""
        # a folder or FIFO at the CSV's path is refused by the reader, not taken for "no CSV yet": no save could land
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
        return pairs, others

    def _advance(self, pairs: list[list[float]]) -> None:
        """A new saved state (lock held): the page's next save starts from its revision."""
        if self.history and [_key(p) for p in pairs] == [_key(p) for p in self.history[self.revision]]:
            return
        self.revision += 1
        self.history[self.revision] = [list(p) for p in pairs]
        self.history.pop(self.revision - 1000, None)  # a page a thousand saves behind reloads instead

    @property
    def revision_id(self) -> str:
        return f"{self.token}-{self.revision}"

    def reload(self) -> None:
        """Read the CSV from disk (if it exists): this pair's rows are edited, the others kept."""
        pairs, others = self._read()
        with self.lock:
            self.pairs, self.others = pairs, others
            self._advance(pairs)
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

    def _base(self, revision) -> list[list[float]]:
        token, _, number = str(revision).rpartition("-")
        if token != self.token or not number.isdigit() or int(number) not in self.history:
            raise StalePage(f"this page is older than the picker serving it (revision {revision}); reload the page "
                            "(its last change was not saved)")
        return self.history[int(number)]

    def _backup(self, data: bytes) -> Path:
        """A dated copy of the CSV that no other save replaces."""
        stamp = time.strftime("%Y%m%d-%H%M%S")
        for n in range(1, 10_000):
            path = self.csv_path.with_name(f"{self.csv_path.name}.{stamp}{'' if n == 1 else f'-{n}'}.bak")
            if not os.path.lexists(path):
                return write_bytes_atomic(path, data, overwrite=False)
        raise WorkspaceError(f"too many backups of {self.csv_path} this second")

    def backups(self) -> list[Path]:
        """The dated backups of the CSV, oldest first."""
        return sorted(self.csv_path.parent.glob(f"{self.csv_path.name}.*.bak"), key=lambda p: (p.stat().st_mtime, p.name))

    def _keep_unsaved(self, rows: list[Correspondence], cause: str) -> SaveFailed:
        """Remember the pairs a failed save held, in a file outside the CSV's folder, and say so."""
        self.save_error = f"cannot save to {self.csv_path}: {cause}"
        try:
            if self.rescue is None:
                fd, name = tempfile.mkstemp(prefix="rigsfm-pick-unsaved-", suffix=".csv")
                os.close(fd)
                self.rescue = Path(name)
            write_bytes_atomic(self.rescue, format_manual_matches(rows).encode("utf-8"))
            # rows: unsaved
            kept = f"the {len(self.unsaved)} pairs of this page are kept in {self.rescue}"  # type: ignore[arg-type]
        except OSError:
            kept = "the page still holds its pairs"
        return SaveFailed(f"{self.save_error}; nothing saved was changed and {kept}; fix the folder (or copy that "
                          "file) and save again")

    def set_pairs(self, pairs, revision=None) -> dict:
        """Save this image pair's correspondences (temporary file + rename). With ``revision`` (the state the page's
        pairs started from) a page that is behind has its own edit applied to the newer pairs; a save that still
        drops more than one saved pair first keeps the CSV in a dated backup (see the module docstring)."""
        if not isinstance(pairs, list):
            raise ManualMatchError("'pairs' must be a list of [x_a, y_a, x_b, y_b]")
        clean = self._check(pairs)
        a, b = (image.name for image in self.images)
        backup = None
        with self.lock:
            base = self._base(revision) if revision is not None else None
            current, others = self.pairs, self.others  # the CSV gone (or its folder): what was last saved here
            if self.csv_path.is_file():
                try:
                    current, others = self._read()
                except (ManualMatchError, OSError) as error:  # edited into a broken file meanwhile: left as it is
                    self.unsaved = clean
                    cause = str(error) if isinstance(error, ManualMatchError) else os_error_text(error)
                    raise self._keep_unsaved(others + [Correspondence(a, (p[0], p[1]), b, (p[2], p[3]))
                                                       for p in clean], cause) from None
            result = merge(current, base, clean) if base is not None else clean
            if base is not None and result is not clean:
                logger.warning("A page behind the saved pairs of %s <-> %s saved: its edit was applied to the %d newer "
                               "pairs", a, b, len(current))
            kept = {_key(p) for p in result}
            lost = [p for p in current if _key(p) not in kept]
            rows = others + [Correspondence(a, (p[0], p[1]), b, (p[2], p[3])) for p in result]
            self.unsaved = result
            try:
                if len(lost) > 1 and self.csv_path.is_file():
                    backup = self._backup(self.csv_path.read_bytes())
                    logger.warning("This save drops %d of the %d saved pairs of %s <-> %s: the CSV as it was is kept "
                                   "in %s", len(lost), len(current), a, b, backup)
                write_manual_matches(self.csv_path, rows)
            except OSError as error:
                blocked = any(folder.exists() and not folder.is_dir() for folder in self.csv_path.parents)
                cause = "a part of the path is a file, not a folder" if blocked else os_error_text(error)  # EEXIST
                raise self._keep_unsaved(rows, cause) from None
            self.unsaved, self.save_error = None, ""
            self.pairs, self.others = result, others
            self._advance(result)
            self._refit()
        logger.info("Saved %d pairs to %s", len(result), self.csv_path)
        state = self.state()
        if backup is not None:
            state["backup"] = str(backup)
        return state

    def state(self) -> dict:
        with self.lock:
            return {
                "images": [{"name": i.name, "width": i.width, "height": i.height} for i in self.images],
                "csv": str(self.csv_path),
                "revision": self.revision_id,
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
