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
from rigsfm.run.inputs import ImageEntry
from rigsfm.core.io import load_yaml_or_json


DEFAULT_DISTANCE_SIGMA = 0.01
DEFAULT_LENGTH_SIGMA = 0.002
DEFAULT_PIXEL_SIGMA = 0.5


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
    except (TypeError, ValueError) as e:
        raise InputError(f"{where} must be a number, got {value!r}") from e
    if not np.isfinite(number) or number <= 0:
        raise InputError(f"{where} must be positive, got {value}")
    return number


def _meters(value, where: str) -> float:
    return _positive(value, f"{where}: 'meters'")


def _pixel(value, where: str) -> tuple[float, float]:
    try:
        xy = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: expected [x, y] pixel coordinates") from e
    if xy.shape != (2,) or not np.all(np.isfinite(xy)):
        raise InputError(f"{where}: expected [x, y] pixel coordinates, got {value}")
    return float(xy[0]), float(xy[1])


def load_scale(path: Path, images: Sequence[ImageEntry]) -> ScaleSpec:
    """Read scale.yaml and check every camera and image it names exists in the image folder."""
    path = Path(path)
    data = load_yaml_or_json(path, "scale")
    unknown = set(data) - {"camera_distance", "known_length", "pixel_sigma"}
    if unknown:
        raise InputError(
            f"{path}: unknown key(s) {', '.join(sorted(unknown))}; use camera_distance, known_length, pixel_sigma"
        )
    pixel_sigma = _positive(data.get("pixel_sigma", DEFAULT_PIXEL_SIGMA), f"{path}: pixel_sigma")
    image_names = {entry.name for entry in images}
    camera_names = {f"{entry.rig}/{entry.sensor}" for entry in images}

    distances = []
    for i, item in enumerate(data.get("camera_distance") or []):
        where = f"{path}: camera_distance[{i}]"
        if not isinstance(item, dict) or not {"a", "b", "meters"} <= set(item):
            raise InputError(f"{where}: expected {{a: rig/sensor, b: rig/sensor, meters: number}}")
        for key in ("a", "b"):
            if item[key] not in camera_names and item[key] not in image_names:
                raise InputError(
                    f"{where}: {key} = {item[key]!r} names no camera or image in the image folder "
                    "(write <rig>/<sensor> or <rig>/<sensor>/<frame file>)"
                )
        if item["a"] == item["b"]:
            raise InputError(f"{where}: a and b are the same camera")
        sigma = _positive(item.get("sigma", DEFAULT_DISTANCE_SIGMA), f"{where}: sigma")
        distances.append(CameraDistance(str(item["a"]), str(item["b"]), _meters(item["meters"], where), sigma))

    lengths = []
    for i, item in enumerate(data.get("known_length") or []):
        where = f"{path}: known_length[{i}]"
        if not isinstance(item, dict) or "meters" not in item or not isinstance(item.get("observations"), list):
            raise InputError(f"{where}: expected {{meters: number, observations: [...]}}")
        observations = []
        for j, obs in enumerate(item["observations"]):
            obs_where = f"{where}.observations[{j}]"
            if not isinstance(obs, dict) or not {"image", "a", "b"} <= set(obs):
                raise InputError(f"{obs_where}: expected {{image: name, a: [x, y], b: [x, y]}}")
            if obs["image"] not in image_names:
                raise InputError(f"{obs_where}: image {obs['image']!r} is not in the image folder")
            observations.append(
                LengthObservation(str(obs["image"]), _pixel(obs["a"], obs_where), _pixel(obs["b"], obs_where))
            )
        if len({o.image for o in observations}) < 2:
            raise InputError(f"{where}: needs the object's two ends seen in at least two different images")
        sigma = _positive(item.get("sigma", DEFAULT_LENGTH_SIGMA), f"{where}: sigma")
        lengths.append(KnownLength(_meters(item["meters"], where), tuple(observations), sigma))

    if not distances and not lengths:
        raise InputError(f"{path}: no measurement; give camera_distance and/or known_length entries")
    return ScaleSpec(path, tuple(distances), tuple(lengths), pixel_sigma)
