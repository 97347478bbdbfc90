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
or a full image name ``<rig>/<sensor>/<frame file>``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigsfm.core.errors import InputError
from rigsfm.core.io import load_yaml_or_json
from rigsfm.core.rig import RigCalibration, check_keys
from rigsfm.run.inputs import ImageEntry


DEFAULT_DISTANCE_SIGMA = 0.01
DEFAULT_LENGTH_SIGMA = 0.002
DEFAULT_PIXEL_SIGMA = 0.5
MIN_END_SEPARATION_PX = 1.0  # a known length whose two ends are closer in an image is a repeated point


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


def _positive(value, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{where} must be a number, got {value!r}") from e
    if not np.isfinite(number) or number <= 0:
        raise InputError(f"{where} must be positive, got {value}")
    return number


def _meters(value, where: str) -> float:
    return _positive(value, f"{where}: 'meters'")


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
        raise InputError(f"{where}: ({x:g}, {y:g}) lies outside {entry.name}, which is {camera.width}x{camera.height} "
                         "px (COLMAP pixels: 0 <= x <= width, 0 <= y <= height); fix the coordinates")


def load_scale(path: Path, images: Sequence[ImageEntry], rigs: Sequence[RigCalibration] | None = None) -> ScaleSpec:
    """Read scale.yaml and check every camera and image it names exists in the image folder; with ``rigs``, also
    that every known-length end point lies inside its image."""
    path = Path(path)
    by_rig = None if rigs is None else {rig.name: rig for rig in rigs}
    entries = {entry.name: entry for entry in images}
    data = load_yaml_or_json(path, "scale")
    check_keys(data, ("camera_distance", "known_length", "pixel_sigma"), str(path))
    pixel_sigma = _positive(data.get("pixel_sigma", DEFAULT_PIXEL_SIGMA), f"{path}: pixel_sigma")
    image_names = {entry.name for entry in images}
    camera_names = {f"{entry.rig}/{entry.sensor}" for entry in images}

    distances = []
    for i, item in enumerate(_list(data, "camera_distance", path)):
        where = f"{path}: camera_distance[{i}]"
        if not isinstance(item, dict) or not {"a", "b", "meters"} <= set(item):
            raise InputError(f"{where}: expected {{a: rig/sensor, b: rig/sensor, meters: number}}")
        check_keys(item, ("a", "b", "meters", "sigma"), where)
        for key in ("a", "b"):
            if not isinstance(item[key], str) or (item[key] not in camera_names and item[key] not in image_names):
                raise InputError(
                    f"{where}: {key} = {item[key]!r} names no camera or image in the image folder "
                    "(write <rig>/<sensor> or <rig>/<sensor>/<frame file>)"
                )
        if item["a"] == item["b"] or str(item["a"]).startswith(f"{item['b']}/") or \
                str(item["b"]).startswith(f"{item['a']}/"):
            raise InputError(f"{where}: a = {item['a']!r} and b = {item['b']!r} are the same camera (zero distance); "
                             "measure between two different cameras")
        sigma = _positive(item.get("sigma", DEFAULT_DISTANCE_SIGMA), f"{where}: sigma")
        distances.append(CameraDistance(str(item["a"]), str(item["b"]), _meters(item["meters"], where), sigma))

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
            if not isinstance(obs["image"], str) or obs["image"] not in image_names:
                raise InputError(f"{obs_where}: image {obs['image']!r} is not in the image folder")
            a, b = _pixel(obs["a"], f"{obs_where}.a"), _pixel(obs["b"], f"{obs_where}.b")
            _check_inside(a, entries[obs["image"]], by_rig, f"{obs_where}.a")
            _check_inside(b, entries[obs["image"]], by_rig, f"{obs_where}.b")
            if np.hypot(a[0] - b[0], a[1] - b[1]) < MIN_END_SEPARATION_PX:
                raise InputError(f"{obs_where}: a and b are the same point in {obs['image']} (a zero-length bar); give "
                                 "the pixels of the object's two different ends")
            observations.append(LengthObservation(str(obs["image"]), a, b))
        if len({o.image for o in observations}) < 2:
            raise InputError(f"{where}: needs the object's two ends seen in at least two different images")
        sigma = _positive(item.get("sigma", DEFAULT_LENGTH_SIGMA), f"{where}: sigma")
        lengths.append(KnownLength(_meters(item["meters"], where), tuple(observations), sigma))

    if not distances and not lengths:
        raise InputError(f"{path}: no measurement; give camera_distance and/or known_length entries")
    return ScaleSpec(path, tuple(distances), tuple(lengths), pixel_sigma)
