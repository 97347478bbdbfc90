"""The metric scale file (scale.yaml): rangefinder distances and objects of known length.

```yaml
camera_distance: [{a: rig01/wide, b: rig05/wide, meters: 27.97}]
known_length:
  - meters: 2.0
    observations:
      - {image: rig01/wide/frame0000.png, a: [x, y], b: [x, y]}    # COLMAP pixels
      - {image: rig02/wide/frame0000.png, a: [x, y], b: [x, y]}
```
Each measurement may carry ``sigma`` (metres, its standard uncertainty; default 0.01 for a camera
distance, 0.002 for a known length); the pixel observations of known lengths have ``pixel_sigma``
(top level, default 0.5 px). Measurements are weighted by their total uncertainty.
A camera in ``camera_distance`` is ``<rig>/<sensor>`` (the camera's centre, averaged over its frames)
or a full image name ``<rig>/<sensor>/<frame file>``; names are compared Unicode-normalised (NFC).

Besides the syntax, :func:`load_scale` refuses numbers no real measurement has: a distance or length that is not
a finite number of metres within 1 mm - 2 km (0.01 m for a distance between rigs), a sigma below what any
instrument gives or above the value itself, and a distance between the two sensors of one rig (its
narrow_from_wide fixes it already; one that contradicts it is named with both numbers).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigsfm.core.errors import InputError
from rigsfm.core.io import load_yaml_or_json
from rigsfm.core.rig import RigCalibration, check_keys, nfc
from rigsfm.run.inputs.images import ImageEntry

DEFAULT_DISTANCE_SIGMA = 0.01
DEFAULT_LENGTH_SIGMA = 0.002
DEFAULT_PIXEL_SIGMA = 0.5
MIN_END_SEPARATION_PX = 1.0  # a known length whose two ends are closer in an image is a repeated point
# What real measurements are: laser rangefinders reach ~2 km; two rigs stand at least a few cm apart; no tape
# or rangefinder is better than 0.1 mm, no bar's length known better than 10 um (smaller sigmas overflow the
# adjustment's weights).
MAX_METERS = 2000.0
MIN_DISTANCE_M = 0.01
MIN_LENGTH_M = 0.001
MIN_DISTANCE_SIGMA_M = 1e-4
MIN_LENGTH_SIGMA_M = 1e-5
PIXEL_SIGMA_RANGE = (0.01, 20.0)


@dataclass(frozen=True)
class CameraDistance:
    a: str
    b: str
    meters: float
    sigma: float = DEFAULT_DISTANCE_SIGMA


@dataclass(frozen=True)
class LengthObservation:
    image: str
    a: tuple[float, float]
    b: tuple[float, float]


@dataclass(frozen=True)
class KnownLength:
    meters: float
    observations: tuple[LengthObservation, ...]
    sigma: float = DEFAULT_LENGTH_SIGMA


@dataclass(frozen=True)
class ScaleSpec:
    path: Path
    camera_distances: tuple[CameraDistance, ...]
    known_lengths: tuple[KnownLength, ...]
    pixel_sigma: float = DEFAULT_PIXEL_SIGMA


def _number(value, where: str, low: float, high: float, unit: str, why: str) -> float:
    """``value`` as a float in [low, high]; otherwise an ``InputError`` naming the key, the range and ``why``."""
    if isinstance(value, bool) or isinstance(value, str) and "," in value:
        hint = "; write decimals with a point" if isinstance(value, str) else ""
        raise InputError(f"{where} must be a number, got {value!r}{hint}")
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{where} must be a number, got {value!r}") from e
    if not np.isfinite(number) or not low <= number <= high:
        raise InputError(f"{where} must be a finite number {low:g} - {high:g} {unit}, got {value!r}: {why}")
    return number


def _positive(value, where: str, low: float = 1e-12, high: float = 1e12, unit: str = "",
              why: str = "it is a measurement's size") -> float:
    return _number(value, where, low, high, unit, why)


def _meters(value, where: str, low: float) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        number = math.nan
    why = ("a measured size is more than zero" if number <= 0 else "a measurement is a finite number of metres"
           if not math.isfinite(number) and not math.isnan(number) else
           "a measured size in metres (millimetres or another unit?)")
    return _number(value, f"{where}: 'meters'", low, MAX_METERS, "m", why)


def _list(data: dict, key: str, path: Path) -> list:
    value = data.get(key)
    if value is None:
        return []
    if not isinstance(value, list):
        raise InputError(f"{path}: {key} must be a list of entries (each starting with '- '), got {value!r}")
    return value


def _pixel(value, where: str) -> tuple[float, float]:
    try:
        xy = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{where}: expected [x, y] pixel coordinates") from e
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise InputError(f"{where}: expected [x, y] pixel coordinates, got {value}")
    return float(xy[0]), float(xy[1])


def _check_inside(xy: tuple[float, float], entry: ImageEntry, rigs: dict[str, RigCalibration] | None,
                  where: str) -> None:
    if rigs is None or entry.rig not in rigs:
        return
    camera = rigs[entry.rig].camera(entry.sensor)
    x, y = xy
    if not (0.0 <= x <= camera.width and 0.0 <= y <= camera.height):
        raise InputError(f"{where}: ({x:g}, {y:g}) lies outside '{entry.name}', which is {camera.width}x{camera.height} "
                         "px (COLMAP pixels: 0 <= x <= width, 0 <= y <= height); fix the coordinates")


def _refuse_within_rig(where: str, item: dict, meters: float, rig: RigCalibration | None) -> None:
    """A distance between the two sensors of one rig is its baseline |t|, which narrow_from_wide fixes: it cannot
    set the network's scale (and fails the adjustment). Refused, saying whether it even agrees with |t|."""
    head = f"{where}: a = {item['a']!r} and b = {item['b']!r} are the two sensors of one rig"
    if rig is None:
        raise InputError(f"{head}; their distance is fixed by narrow_from_wide: measure between two rigs")
    baseline = float(np.linalg.norm(rig.narrow_from_wide.translation))
    agrees = abs(meters - baseline) <= max(0.005, 0.1 * baseline)
    verdict = "agrees with" if agrees else "contradicts"
    raise InputError(f"{head}; {meters:g} m {verdict} their narrow_from_wide baseline |t| = {baseline:.4g} m, which "
                     "fixes it already and cannot set the network's scale: measure between two rigs")


def load_scale(path: Path, images: Sequence[ImageEntry], rigs: Sequence[RigCalibration] | None = None) -> ScaleSpec:
    """Read scale.yaml and check every camera and image it names exists in the image folder; with ``rigs``, also
    that every known-length end point lies inside its image."""
    path = Path(path)
    by_rig = None if rigs is None else {rig.name: rig for rig in rigs}
    entries = {entry.name: entry for entry in images}
    data = load_yaml_or_json(path, "scale", form="it holds 'camera_distance:' and/or 'known_length:' lists "
                                                  "(docs/inputs.md, Metric scale)")
    check_keys(data, ("camera_distance", "known_length", "pixel_sigma"), str(path))
    pixel_sigma = _positive(data.get("pixel_sigma", DEFAULT_PIXEL_SIGMA), f"{path}: pixel_sigma", *PIXEL_SIGMA_RANGE,
                            "px", "a clicked point's 1-sigma error in pixels")
    # NFC name -> the name as on disk (what the workspace uses)
    image_names = {nfc(entry.name): entry.name for entry in images}
    camera_names = {nfc(f"{entry.rig}/{entry.sensor}"): f"{entry.rig}/{entry.sensor}" for entry in images}
    rig_of = {nfc(entry.name): entry.rig for entry in images} | {nfc(f"{e.rig}/{e.sensor}"): e.rig for e in images}
    sensor_of = {nfc(e.name): e.sensor for e in images} | {nfc(f"{e.rig}/{e.sensor}"): e.sensor for e in images}

    distances = []
    for i, item in enumerate(_list(data, "camera_distance", path)):
        where = f"{path}: camera_distance[{i}]"
        if not isinstance(item, dict) or not {"a", "b", "meters"} <= set(item):
            raise InputError(f"{where}: expected {{a: rig/sensor, b: rig/sensor, meters: number}}")
        check_keys(item, ("a", "b", "meters", "sigma"), where)
        ends = {}
        for key in ("a", "b"):
            if not isinstance(item[key], str) or (nfc(item[key]) not in camera_names
                                                  and nfc(item[key]) not in image_names):
                raise InputError(
                    f"{where}: {key} = {item[key]!r} names no camera or image in the image folder "
                    "(write <rig>/<sensor> or <rig>/<sensor>/<frame file>)"
                )
            ends[key] = nfc(item[key])
        a, b = ends["a"], ends["b"]
        if rig_of[a] == rig_of[b] and sensor_of[a] == sensor_of[b]:
            raise InputError(f"{where}: a = {item['a']!r} and b = {item['b']!r} are the same camera (zero distance); "
                             "measure between two different cameras")
        meters = _meters(item["meters"], where, MIN_LENGTH_M)
        if rig_of[a] == rig_of[b]:
            _refuse_within_rig(where, item, meters, by_rig.get(rig_of[a]) if by_rig else None)
        if meters < MIN_DISTANCE_M:
            raise InputError(f"{where}: 'meters' = {meters:g} m between two rigs, which stand at least "
                             f"{MIN_DISTANCE_M:g} m apart; give the distance in metres")
        sigma = _positive(item.get("sigma", DEFAULT_DISTANCE_SIGMA), f"{where}: sigma", MIN_DISTANCE_SIGMA_M, meters, "m",
                          f"a rangefinder's 1-sigma error, at least {MIN_DISTANCE_SIGMA_M * 1000:g} mm and at most the "
                          "distance itself")
        distances.append(CameraDistance(camera_names.get(a) or image_names[a], camera_names.get(b) or image_names[b],
                                        meters, sigma))

    lengths = []
    for i, item in enumerate(_list(data, "known_length", path)):
        where = f"{path}: known_length[{i}]"
        if not isinstance(item, dict) or "meters" not in item or not isinstance(item.get("observations"), list):
            raise InputError(f"{where}: expected {{meters: number, observations: [...]}}")
        check_keys(item, ("meters", "observations", "sigma"), where)
        observations = []
        for j, obs in enumerate(item["observations"]):
            obs_where = f"{where}.observations[{j}]"
            if not isinstance(obs, dict) or not {"image", "a", "b"} <= set(obs):
                raise InputError(f"{obs_where}: expected {{image: name, a: [x, y], b: [x, y]}}")
            check_keys(obs, ("image", "a", "b"), obs_where)
            if not isinstance(obs["image"], str) or nfc(obs["image"]) not in image_names:
                raise InputError(f"{obs_where}: image {obs['image']!r} is not in the image folder")
            image = image_names[nfc(obs["image"])]
            end_a, end_b = _pixel(obs["a"], f"{obs_where}.a"), _pixel(obs["b"], f"{obs_where}.b")
            _check_inside(end_a, entries[image], by_rig, f"{obs_where}.a")
            _check_inside(end_b, entries[image], by_rig, f"{obs_where}.b")
            if np.hypot(end_a[0] - end_b[0], end_a[1] - end_b[1]) < MIN_END_SEPARATION_PX:
                raise InputError(f"{obs_where}: a and b are the same point in '{obs['image']}' (a zero-length bar); give "
                                 "the pixels of the object's two different ends")
            observations.append(LengthObservation(image, end_a, end_b))
        if len({o.image for o in observations}) < 2:
            raise InputError(f"{where}: needs the object's two ends seen in at least two different images")
        meters = _meters(item["meters"], where, MIN_LENGTH_M)
        sigma = _positive(item.get("sigma", DEFAULT_LENGTH_SIGMA), f"{where}: sigma", MIN_LENGTH_SIGMA_M, meters, "m",
                          f"the length's 1-sigma error, at least {MIN_LENGTH_SIGMA_M * 1e6:g} um and at most the length "
                          "itself")
        lengths.append(KnownLength(meters, tuple(observations), sigma))

    if not distances and not lengths:
        raise InputError(f"{path}: no measurement; give camera_distance and/or known_length entries")
    return ScaleSpec(path, tuple(distances), tuple(lengths), pixel_sigma)
