"""Manual correspondences between wide images: the CSV format, its validation, and the database merge.

CSV, one correspondence per line (a header line ``image_a,x_a,y_a,image_b,x_b,y_b`` is allowed, lines
starting with ``#`` are comments)::

    image_a,x_a,y_a,image_b,x_b,y_b
    rig01/wide/frame0000.png,512.25,300.5,rig02/wide/frame0000.png,140.0,288.75

Image names are the workspace names ``<rig>/wide/<frame file>`` (relative to the image folder). Pixel
coordinates follow COLMAP: the image spans [0, width] x [0, height], the centre of the top-left pixel
is (0.5, 0.5) (OpenCV's (0, 0)); ``rigsfm pick`` writes exactly this.

Merge (:func:`rigsfm.run.matching.manual_merge.add_manual_matches`): every manual point becomes a keypoint appended after the image's
automatic keypoints (descriptor row of zeros, so it never wins a descriptor match); each pair's manual
correspondences are verified alone (calibrated RANSAC, essential matrix with the calibrated intrinsics),
their inliers are united with the pair's automatic matches, and the union is verified again and
replaces the pair's two-view geometry.
"""

from __future__ import annotations

import csv
import difflib
import io
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.io import read_user_text, write_text_atomic
from rigsfm.core.rig import RigCalibration, nfc
from rigsfm.run.inputs.images import ImageEntry

logger = logging.getLogger(__name__)

HEADER = ("image_a", "x_a", "y_a", "image_b", "x_b", "y_b")
MIN_CORRESPONDENCES = 8  # per image pair: enough for the 5-point RANSAC to reject a couple of outliers
MIN_SPREAD_FRACTION = 0.02  # RMS distance from the best-fit line, as a fraction of the image diagonal


class ManualMatchError(InputError):
    """The manual correspondence file is malformed or refers to something that does not exist."""


class TooFewCorrespondencesError(ManualMatchError):
    """An image pair has fewer (consistent) manual correspondences than the pose estimator needs."""


class DegenerateCorrespondencesError(ManualMatchError):
    """The correspondences of a pair cannot determine a relative pose (collinear, or one plane)."""


@dataclass(frozen=True)
class Correspondence:
    image_a: str
    xy_a: tuple[float, float]
    image_b: str
    xy_b: tuple[float, float]
    line: int = 0  # line number in the CSV (0: not from a file)

    def swapped(self) -> Correspondence:
        return Correspondence(self.image_b, self.xy_b, self.image_a, self.xy_a, self.line)


def read_manual_matches(path: Path) -> list[Correspondence]:
    """Parse the CSV (syntax only); raises ``ManualMatchError`` naming the line to fix."""
    path = Path(path)
    try:
        text = read_user_text(path, "manual matches")
    except InputError as error:
        raise ManualMatchError(str(error)) from None
    rows = []
    if "\0" in text:
        raise ManualMatchError(f"{path}: holds NUL characters (a binary file, or UTF-16 without its byte-order mark); "
                               "save it as CSV UTF-8")
    for line, row in enumerate(csv.reader(io.StringIO(text, newline="")), start=1):
        cells = [c.strip() for c in row]
        if not any(cells) or cells[0].startswith("#"):
            continue
        if tuple(c.lower() for c in cells) == HEADER:
            continue
        if len(cells) != 6:
            separator = next((name for sep, name in ((";", "semicolons"), ("\t", "tabs")) if len(cells) == 1
                              and cells[0].count(sep) == 5), None)
            raise ManualMatchError(
                f"{path}:{line}: " + (f"the columns are separated by {separator}; save it as comma-separated CSV"
                                      if separator else
                                      f"expected 6 columns {','.join(HEADER)}, got {len(cells)}: {','.join(cells)}")
            )
        try:
            xa, ya, xb, yb = (float(cells[i]) for i in (1, 2, 4, 5))
        except ValueError:
            raise ManualMatchError(
                f"{path}:{line}: x and y must be numbers (pixels), got {','.join(cells)}"
            ) from None
        if not all(math.isfinite(v) for v in (xa, ya, xb, yb)):
            raise ManualMatchError(f"{path}:{line}: coordinates must be finite numbers")
        rows.append(Correspondence(cells[0], (xa, ya), cells[3], (xb, yb), line))
    return rows


def format_manual_matches(rows: Sequence[Correspondence]) -> str:
    lines = [",".join(HEADER)]
    lines += [
        f"{r.image_a},{r.xy_a[0]:.3f},{r.xy_a[1]:.3f},{r.image_b},{r.xy_b[0]:.3f},{r.xy_b[1]:.3f}"
        for r in rows
    ]
    return "\n".join(lines) + "\n"


def write_manual_matches(path: Path, rows: Sequence[Correspondence]) -> Path:
    """Write the CSV atomically (temporary file, then rename)."""
    return write_text_atomic(Path(path), format_manual_matches(rows))


def group_by_pair(rows: Sequence[Correspondence]) -> dict[tuple[str, str], list[Correspondence]]:
    """Correspondences per unordered image pair, oriented so that ``image_a < image_b``."""
    pairs: dict[tuple[str, str], list[Correspondence]] = {}
    for row in rows:
        row = row if row.image_a < row.image_b else row.swapped()
        pairs.setdefault((row.image_a, row.image_b), []).append(row)
    return pairs


def _line_rms(points: np.ndarray) -> float:
    """RMS distance of 2-D points from their best-fit line."""
    centred = points - points.mean(axis=0)
    return float(np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(len(points)))


def check_spread(points: np.ndarray, camera: pycolmap.Camera, what: str, image: str) -> None:
    """Raise ``DegenerateCorrespondencesError`` if the points hug one line (a thin strip or a line)."""
    rms = _line_rms(np.asarray(points, np.float64))
    if rms < MIN_SPREAD_FRACTION * math.hypot(camera.width, camera.height):
        raise DegenerateCorrespondencesError(
            f"{what} lie (nearly) on one line in {image} (RMS {rms:.1f} px from it), which leaves the relative "
            "pose undetermined; spread the points over the image and over different depths"
        )


def _check_point(path: Path, row: Correspondence, name: str, xy, camera: pycolmap.Camera) -> None:
    x, y = xy
    if not (0.0 <= x <= camera.width and 0.0 <= y <= camera.height):
        raise ManualMatchError(
            f"{path}:{row.line}: point ({x:g}, {y:g}) lies outside '{name}', which is {camera.width}x"
            f"{camera.height} px (COLMAP pixels: 0 <= x <= width, 0 <= y <= height); fix the coordinates"
        )


def validate_manual_matches(
    path: Path, rows: Sequence[Correspondence], images: Sequence[ImageEntry], rigs: Sequence[RigCalibration]
) -> dict[tuple[str, str], list[Correspondence]]:
    """Check names, bounds, counts and spread against the inputs; returns the rows grouped by pair."""
    path = Path(path)
    if not rows:
        raise TooFewCorrespondencesError(f"{path} holds no correspondences; add lines {','.join(HEADER)}")
    entries = {e.name: e for e in images}
    on_disk = {nfc(e.name): e.name for e in images}  # names are compared Unicode-normalised, kept as on disk
    rows = [replace(row, image_a=on_disk.get(nfc(row.image_a), row.image_a),
                    image_b=on_disk.get(nfc(row.image_b), row.image_b)) for row in rows]
    wide = sorted(n for n, e in entries.items() if e.sensor == "wide")
    cameras = {rig.name: rig.wide for rig in rigs}
    for row in rows:
        for name in (row.image_a, row.image_b):
            if name not in entries or entries[name].sensor != "wide":
                hint = difflib.get_close_matches(name, wide, n=1)
                raise ManualMatchError(
                    f"{path}:{row.line}: unknown wide image {name!r}"
                    + (f" (did you mean {hint[0]!r}?)" if hint else f" (e.g. {wide[0]!r})")
                    + "; names are <rig>/wide/<file> relative to the image folder"
                )
        if row.image_a == row.image_b:
            raise ManualMatchError(
                f"{path}:{row.line}: both points are in {row.image_a}; pair two different images"
            )
        _check_point(path, row, row.image_a, row.xy_a, cameras[entries[row.image_a].rig])
        _check_point(path, row, row.image_b, row.xy_b, cameras[entries[row.image_b].rig])
    pairs = group_by_pair(rows)
    for (a, b), group in pairs.items():
        if len(group) < MIN_CORRESPONDENCES:
            raise TooFewCorrespondencesError(
                f"{path}: '{a}' <-> '{b}' has {len(group)} correspondence(s); the calibrated relative pose "
                f"(5-point RANSAC) needs at least {MIN_CORRESPONDENCES}; add {MIN_CORRESPONDENCES - len(group)} "
                "more (rigsfm pick helps) or remove this pair"
            )
        for name, xy in ((a, [r.xy_a for r in group]), (b, [r.xy_b for r in group])):
            check_spread(
                np.asarray(xy),
                cameras[entries[name].rig],
                f"{path}: the {len(group)} points of '{a}' <-> '{b}'",
                name,
            )
    return pairs
