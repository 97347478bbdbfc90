"""The detections CSV: ``image, x, y[, score][, label][, radius]``, one row per point in a narrow image, COLMAP
pixels.

Every problem is refused before anything is computed or written, with one line naming the row (its line in the
file) and the fix. A row with an image and empty ``x`` and ``y`` declares an image that was analysed and holds no
detection (an empty view, or with every image of a frame so, an empty frame). ``radius``: the detection's apparent
head radius (px, e.g. half its head box's width), evidence of its depth; a frame's detections give it on every row or
on none (then the size cue is off for that frame), since a cue on some detections only would score them unlike the
others.
"""

from __future__ import annotations

import csv
import io
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigsfm.core.errors import InputError
from rigsfm.core.io import read_user_text
from rigsfm.core.names import ImageName, Sensor, quoted

logger = logging.getLogger(__name__)

REQUIRED = ("image", "x", "y")
OPTIONAL = ("score", "label", "radius")


@dataclass
class ImageDetections:
    """The detections of one narrow image, in the order of the file."""

    image: str
    xy: np.ndarray  # N x 2, COLMAP pixels (raw, distorted)
    rows: np.ndarray  # N: line numbers in the CSV (header = 1)
    text: list[tuple[str, str]] = field(default_factory=list)  # x, y exactly as given
    score: np.ndarray | None = None
    label: list[str] | None = None
    radius: np.ndarray | None = None  # N: apparent head radius (px), where the file gives the radius column

    def __len__(self) -> int:
        return len(self.xy)


@dataclass
class Detections:
    """Per image name, its detections; ``frames`` groups the images by frame file name (synchronised)."""

    images: dict[str, ImageDetections]
    source: str = ""

    def frames(self) -> dict[str, list[str]]:
        out: dict[str, list[str]] = {}
        for name in self.images:
            out.setdefault(ImageName.parse(name).frame, []).append(name)
        return dict(sorted(out.items()))


def from_arrays(points: dict[str, np.ndarray], radii: dict[str, np.ndarray] | None = None) -> Detections:
    """Detections from arrays per image name (N x 2 COLMAP pixels; ``radii``: N apparent head radii, px, per image);
    rows count from 2 in the images' order."""
    images, row = {}, 2
    for name, xy in points.items():
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        rows = np.arange(row, row + len(xy))
        row += max(len(xy), 1)
        radius = np.asarray(radii[name], dtype=np.float64).reshape(-1) if radii is not None else None
        images[name] = ImageDetections(name, xy, rows, [(repr(float(a)), repr(float(b))) for a, b in xy],
                                       radius=radius)
    return Detections(images, "arrays")


def _fail(path: Path, line: int, what: str) -> InputError:
    return InputError(f"{path} line {line}: {what}")


def _radius(path: Path, line: int, text: str, size: tuple[int, int]) -> float | None:
    """A row's apparent head radius (px), None where it is empty; a head wider than half the image is no head."""
    if not text:
        return None
    try:
        radius = float(text)
    except ValueError:
        raise _fail(path, line, f"radius {text!r} is not a number; give the head's apparent radius in pixels "
                                "(a decimal point, not a comma)") from None
    limit = min(size) / 2
    if not (math.isfinite(radius) and 0 < radius < limit):
        raise _fail(path, line, f"radius {text} is not a head's apparent radius in this {size[0]} x {size[1]} px "
                                f"image (0 < radius < {limit:g} px); give half the head box's width in pixels")
    return radius


def read_detections(path: Path, sizes: dict[str, tuple[int, int]], known: set[str],
                    stand_in: Mapping[str, tuple[int, int]] | None = None, poses_from: str | None = None) -> Detections:
    """Parse and check ``path``. ``sizes``: width, height of every registered narrow image; ``known``: every image
    name the run was given (registered or not), to tell an unknown image from a frame the run did not register;
    ``stand_in``: per camera (``<rig>/narrow``), the image size of the run's frame ``poses_from`` whose pose stands
    in for frames the run was not given (``--poses-from``); None: such frames are refused."""
    path = Path(path)
    text = read_user_text(path, "detections")
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise InputError(f"{path} line 1: no header; the first line must be 'image,x,y' (optionally ',score,label,radius')")
    header_line = lines[0]
    if ";" in header_line and "," not in header_line:
        raise InputError(f"{path} line 1: columns are separated by semicolons; save it comma-separated "
                         "('CSV UTF-8 (comma delimited)')")
    header = [h.strip().lower() for h in next(csv.reader([header_line]))]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise InputError(f"{path} line 1: missing column(s) {', '.join(missing)}; the header must name image, x, y "
                         f"(optionally score, label, radius), found {', '.join(header) or 'nothing'}")
    col = {name: header.index(name) for name in (*REQUIRED, *OPTIONAL) if name in header}
    images: dict[str, dict] = {}
    seen: dict[tuple[str, float, float], int] = {}
    sized: dict[str, dict[bool, int]] = {}  # per frame, the first line with and the first without a radius
    reader = csv.reader(io.StringIO("\n".join(lines[1:])))
    for offset, fields in enumerate(reader):
        line = offset + 2
        if not fields or all(not f.strip() for f in fields):
            continue
        if len(fields) < len(header):
            if len(fields) == 1 and ";" in fields[0]:
                raise _fail(path, line, "semicolons separate the columns; save it comma-separated")
            raise _fail(path, line, f"{len(fields)} column(s), the header has {len(header)}: give "
                                    f"{', '.join(header)} on every row")
        name = fields[col["image"]].strip()
        try:
            parsed = ImageName.parse(name)
        except ValueError:
            raise _fail(path, line, f"image {name!r} is not a narrow image name <rig>/narrow/<frame file>; use the "
                                    "names of the run's images (OUT/narrow_poses.json)") from None
        if not parsed.is_narrow:
            raise _fail(path, line, f"image {name!r} is a wide image: give detections in the narrow images")
        size = sizes.get(name)
        if size is None and stand_in is not None and name not in known:
            size = stand_in.get(parsed.camera)
        if size is None:
            if name in known:
                raise _fail(path, line, f"image {name!r}: the run registered no model for this frame (no pose); "
                                        "drop its rows, or re-run `rigsfm run` with images that register it")
            if any(k.startswith(parsed.rig + "/") for k in known):
                if stand_in is not None:  # the lending frame lacks this camera: nothing to lend
                    lenders = sorted({ImageName.parse(n).frame for n in sizes
                                      if ImageName.parse(n).camera == parsed.camera})
                    where = (f"pass a frame where it did ({quoted(lenders[:4])}{' ...' if len(lenders) > 4 else ''})"
                             if lenders else f"it registered none in any frame: drop {parsed.rig}'s rows")
                    raise _fail(path, line, f"image {name!r}: the run registered no narrow image of {parsed.rig} "
                                            f"in --poses-from's frame {poses_from!r}, so it has no pose to lend "
                                            f"to this one; {where}")
                # a frame of the run whose wide image came without this narrow one is not a frame it was not given
                if str(ImageName(parsed.rig, Sensor.WIDE, parsed.frame)) in known:
                    given = "was given this frame without this narrow image (only its wide image)"
                elif any(k.endswith("/" + parsed.frame) and ImageName.parse(k).frame == parsed.frame for k in known):
                    given = f"was given this frame without {parsed.rig}'s images"
                else:
                    given = "was not given this frame"
                raise _fail(path, line, f"image {name!r}: the run {given}, so it has no pose for it; re-run "
                                        "`rigsfm run` with its images, or, where the rigs have not moved since, "
                                        "pass --poses-from FRAME (a frame of the run) to use its poses")
            raise _fail(path, line, f"image {name!r} is not an image of this run (rigs and frames in "
                                    "OUT/narrow_poses.json); check the name")
        xs, ys = fields[col["x"]].strip(), fields[col["y"]].strip()
        entry = images.setdefault(name, {"xy": [], "rows": [], "text": [], "score": [], "label": [], "radius": []})
        if not xs and not ys:
            continue  # an analysed image without detections
        try:
            x, y = float(xs), float(ys)
        except ValueError:
            raise _fail(path, line, f"x, y = {xs!r}, {ys!r} are not numbers; give pixel coordinates "
                                    "(a decimal point, not a comma)") from None
        if not (math.isfinite(x) and math.isfinite(y)):
            raise _fail(path, line, f"x, y = {xs}, {ys} are not finite; drop the row or give the point")
        width, height = size
        if not (0.0 <= x <= width and 0.0 <= y <= height):
            raise _fail(path, line, f"({xs}, {ys}) lies outside '{name}' ({width} x {height} px, COLMAP pixels: "
                                    "0..width, 0..height); check the image and the units")
        score = 1.0
        if "score" in col and fields[col["score"]].strip():
            try:
                score = float(fields[col["score"]])
            except ValueError:
                raise _fail(path, line, f"score {fields[col['score']]!r} is not a number") from None
            if not math.isfinite(score):
                raise _fail(path, line, f"score {fields[col['score']]} is not finite; give a number or leave it empty")
        radius = _radius(path, line, fields[col["radius"]].strip(), size) if "radius" in col else None
        sized.setdefault(parsed.frame, {}).setdefault(radius is not None, line)
        key = (name, x, y)  # the point, not its text: 200.25 and 200.250 are one detection
        if key in seen:
            raise _fail(path, line, f"repeats line {seen[key]} ('{name}', {xs}, {ys}); remove the duplicate row")
        seen[key] = line
        entry["xy"].append((x, y))
        entry["rows"].append(line)
        entry["text"].append((xs, ys))
        entry["score"].append(score)
        entry["label"].append(fields[col["label"]].strip() if "label" in col else "")
        entry["radius"].append(radius)
    if not images:
        raise InputError(f"{path}: no rows after the header; give one row per detection: image,x,y")
    for frame, first in sized.items():
        if len(first) == 2:
            late, early = (first[False], first[True]) if first[False] > first[True] else (first[True], first[False])
            has = ("the radius is empty", "gives one") if late == first[False] else ("a radius is given", "has none")
            raise _fail(path, late, f"{has[0]}, but line {early} of the same frame ({frame}) {has[1]}: give every "
                                    "detection of a frame its radius, or none (the size cue is then off for that frame)")
    out = {}
    for name, e in images.items():
        with_radius = "radius" in col and sized.get(ImageName.parse(name).frame, {}).get(True) is not None
        out[name] = ImageDetections(
            name, np.asarray(e["xy"], dtype=np.float64).reshape(-1, 2), np.asarray(e["rows"], dtype=np.int64),
            e["text"], np.asarray(e["score"], dtype=np.float64), e["label"] if "label" in col else None,
            np.asarray(e["radius"], dtype=np.float64).reshape(-1) if with_radius else None)
    logger.info("read %d detections in %d images from %s", sum(len(d) for d in out.values()), len(out), path)
    return Detections(out, str(path))
