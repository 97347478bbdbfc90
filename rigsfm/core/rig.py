"""The rig calibration file (rigs.yaml): per rig, the wide and narrow cameras and E^sl.

```yaml
units: meters
rigs:
  - name: rig01
    sensors:
      wide:   {model: OPENCV, width: 1624, height: 1234, params: [fx, fy, cx, cy, k1, k2, p1, p2]}
      narrow: {model: OPENCV, width: 1624, height: 1234, params: [...]}
    narrow_from_wide:          # x_narrow = R x_wide + t, metres (OpenCV stereoCalibrate's R, T)
      rotation: [[...], [...], [...]]
      translation: [tx, ty, tz]
```
Intrinsics use COLMAP's pixel convention (first pixel centre at (0.5, 0.5)).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import yaml

from rigsfm.core.errors import InputError
from rigsfm.core.names import SENSORS
from rigsfm.core.serialise import camera_to_dict, pose_to_dict
from rigsfm.core.io import load_yaml_or_json, write_text_atomic

CAMERA_MODELS = tuple(m for m in pycolmap.CameraModelId.__members__ if m != "INVALID")
ROTATION_TOLERANCE = 1e-5


@dataclass(frozen=True)
class RigCalibration:
    """One hybrid rig: its two calibrated cameras and ``narrow_from_wide`` (E^sl, metres)."""

    name: str
    wide: pycolmap.Camera
    narrow: pycolmap.Camera
    narrow_from_wide: pycolmap.Rigid3d

    def camera(self, sensor: str) -> pycolmap.Camera:
        return self.wide if sensor == "wide" else self.narrow


def parse_camera(spec, where: str) -> pycolmap.Camera:
    """A ``pycolmap.Camera`` from ``{model, width, height, params}``; ``where`` names it in errors."""
    if not isinstance(spec, dict):
        raise InputError(f"{where}: expected a mapping with model, width, height, params")
    missing = [k for k in ("model", "width", "height", "params") if k not in spec]
    if missing:
        raise InputError(f"{where}: missing {', '.join(missing)}")
    model = str(spec["model"]).upper()
    if model not in CAMERA_MODELS:
        raise InputError(
            f"{where}: unknown camera model {spec['model']!r}; use one of {', '.join(CAMERA_MODELS)}"
        )
    try:
        width, height = int(spec["width"]), int(spec["height"])
        params = [float(p) for p in spec["params"]]
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: width/height must be integers and params a list of numbers") from e
    if width <= 0 or height <= 0:
        raise InputError(f"{where}: width and height must be positive, got {width}x{height}")
    camera = pycolmap.Camera(model=model, width=width, height=height, params=params)
    expected = [p.strip() for p in camera.params_info.split(",")]
    if len(params) != len(expected):
        raise InputError(
            f"{where}: camera model {model} takes {len(expected)} params ({', '.join(expected)}), "
            f"got {len(params)}"
        )
    if not np.all(np.isfinite(params)) or min(camera.focal_length_x, camera.focal_length_y) <= 0:
        raise InputError(f"{where}: params must be finite with positive focal lengths")
    return camera


def parse_rigid3d(spec, where: str) -> pycolmap.Rigid3d:
    """``{rotation: 3x3, translation: 3}`` -> ``pycolmap.Rigid3d``, checking it is a proper rotation."""
    if not isinstance(spec, dict) or "rotation" not in spec or "translation" not in spec:
        raise InputError(f"{where}: expected a mapping with rotation (3x3) and translation (3)")
    try:
        rotation = np.array(spec["rotation"], dtype=np.float64)
        translation = np.array(spec["translation"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: rotation and translation must be numbers") from e
    if rotation.shape != (3, 3) or translation.shape != (3,):
        raise InputError(
            f"{where}: rotation must be 3x3 and translation 3 numbers, "
            f"got {rotation.shape} and {translation.shape}"
        )
    if not (np.all(np.isfinite(rotation)) and np.all(np.isfinite(translation))):
        raise InputError(f"{where}: rotation and translation must be finite")
    orthonormality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if orthonormality > ROTATION_TOLERANCE:
        raise InputError(
            f"{where}: rotation is not orthonormal (max |R^T R - I| = {orthonormality:.2g}); "
            "give the full-precision rotation matrix, e.g. from cv2.stereoCalibrate or cv2.Rodrigues"
        )
    if np.linalg.det(rotation) < 0:
        raise InputError(f"{where}: rotation has det = -1 (a reflection); it must be a proper rotation")
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation)


def load_rigs(path: Path) -> list[RigCalibration]:
    """Read and validate rigs.yaml (or the same structure as JSON)."""
    path = Path(path)
    data = load_yaml_or_json(path, "rig calibration")
    units = data.get("units", "meters")
    if units not in ("meters", "metres", "m"):
        raise InputError(f"{path}: units must be meters (got {units!r}); convert translations to metres")
    entries = data.get("rigs")
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{path}: expected a non-empty list under 'rigs'")
    rigs: list[RigCalibration] = []
    for index, entry in enumerate(entries):
        where = f"{path}: rigs[{index}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str) or not entry["name"]:
            raise InputError(f"{where}: every rig needs a 'name' (its folder name under IMAGES)")
        name = entry["name"]
        if "/" in name or name.startswith("."):
            raise InputError(f"{where}: rig name {name!r} must be a plain folder name")
        where = f"{path}: rig {name}"
        sensors = entry.get("sensors")
        if not isinstance(sensors, dict) or set(sensors) != set(SENSORS):
            raise InputError(f"{where}: 'sensors' must have exactly 'wide' and 'narrow'")
        rigs.append(
            RigCalibration(
                name=name,
                wide=parse_camera(sensors["wide"], f"{where} sensor wide"),
                narrow=parse_camera(sensors["narrow"], f"{where} sensor narrow"),
                narrow_from_wide=parse_rigid3d(entry.get("narrow_from_wide"), f"{where} narrow_from_wide"),
            )
        )
    names = [r.name for r in rigs]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise InputError(f"{path}: rig names must be unique, repeated: {', '.join(duplicates)}")
    return rigs


def rigs_to_yaml(rigs: Sequence[RigCalibration]) -> str:
    data = {
        "units": "meters",
        "rigs": [
            {
                "name": rig.name,
                "sensors": {"wide": camera_to_dict(rig.wide), "narrow": camera_to_dict(rig.narrow)},
                "narrow_from_wide": pose_to_dict(rig.narrow_from_wide, quaternion=False),
            }
            for rig in rigs
        ],
    }
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)


def write_rigs(path: Path, rigs: Sequence[RigCalibration], *, overwrite: bool = False) -> Path:
    """Write rigs.yaml atomically; refuses to replace an existing file unless ``overwrite``."""
    return write_text_atomic(Path(path), rigs_to_yaml(rigs), overwrite=overwrite)


def add_posed_rig(reconstruction: pycolmap.Reconstruction, rig_id: int, calibration: RigCalibration,
                  rig_from_world: pycolmap.Rigid3d, frames: Sequence[dict[str, str]]) -> None:
    """Add one rig to ``reconstruction``: its wide (reference) and narrow cameras (ids ``2 rig_id - 1`` and
    ``2 rig_id``), the rig with E^sl, and one frame at ``rig_from_world`` per entry of ``frames`` (sensor ->
    image name). Frame and image ids continue after the largest ones already there."""
    sensors = {}
    for offset, sensor in enumerate(("wide", "narrow")):
        camera = copy.copy(calibration.camera(sensor))
        camera.camera_id = 2 * rig_id - 1 + offset
        reconstruction.add_camera(camera)
        sensors[sensor] = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera.camera_id)
    rig = pycolmap.Rig(rig_id=rig_id)
    rig.add_ref_sensor(sensors["wide"])
    rig.add_sensor(sensors["narrow"], calibration.narrow_from_wide)
    reconstruction.add_rig(rig)
    frame_id, image_id = max(reconstruction.frames, default=0), max(reconstruction.images, default=0)
    for names in frames:
        frame_id += 1
        frame = pycolmap.Frame(frame_id=frame_id, rig_id=rig_id, rig_from_world=rig_from_world)
        images = []
        for sensor, name in names.items():
            image_id += 1
            images.append(pycolmap.Image(image_id=image_id, name=name, camera_id=sensors[sensor].id,
                                         frame_id=frame_id))
            frame.add_data_id(pycolmap.data_t(sensors[sensor], image_id))
        reconstruction.add_frame(frame)
        for image in images:
            reconstruction.add_image(image)
