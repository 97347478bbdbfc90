"""Camera files for crowd and multi-camera tools: EasyMocap's ``intri.yml``/``extri.yml`` and aniposelib's
``calibration.toml``.

Both layouts hold, per camera, OpenCV intrinsics and the world-to-camera pose:

- ``K``: 3x3 with OpenCV's pixel convention (first pixel centre at (0, 0)): ``cx = cx_colmap - 0.5``.
- distortion in OpenCV's order: ``(k1, k2, p1, p2, k3)`` for SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL and
  OPENCV (zeros where COLMAP's model has no such term), ``(k1, k2, p1, p2, k3, k4, k5, k6)`` (OpenCV's rational
  model) for FULL_OPENCV; for OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE and RADIAL_FISHEYE ``(k1, k2, k3, k4)`` of
  ``cv2.fisheye`` -- only aniposelib's file can say "fisheye" (``fisheye = true``); EasyMocap's reader has no
  such key and always uses the pinhole model, so fisheye cameras are refused there. Other COLMAP models (FOV,
  THIN_PRISM_FISHEYE, RAD_TAN_THIN_PRISM_FISHEYE, DIVISION, ...) have no OpenCV equivalent and are refused.
- ``R`` (Rodrigues 3x1) and ``T`` (3x1): ``x_cam = R x_world + T``, in the reconstruction's world and units
  (metres for ``OUT/sparse``: the floor frame unless the run kept the mapper's, see ``rigsfm.run.world.frame``).

One entry per COLMAP camera (one per rig sensor), named ``<rig>_<sensor>`` (characters other than letters,
digits, ``_`` and ``-`` become ``_``: OpenCV's FileStorage refuses them in keys). Its pose is that of its
registered image; when a camera has several frames the rotations are averaged (chordal mean) and so are the
centres, with a warning when they differ by more than 1 mm or 0.01 deg (rigs are static between frames).

EasyMocap (``easymocap/mytools/camera_utils.py``, ``read_camera``): ``intri.yml`` holds ``names`` (a list of
strings), ``K_<name>`` (3x3), ``dist_<name>`` (1x5 here, 1x8 for FULL_OPENCV), ``H_<name>``/``W_<name>``
(integers, read with ``int(node.real())`` -- absent keys would read as 0); ``extri.yml`` holds ``names``,
``R_<name>`` (Rodrigues 3x1, what the reader uses), ``Rot_<name>`` (3x3, written by EasyMocap's own writer)
and ``T_<name>`` (3x1). Both files start with ``%YAML:1.0`` like OpenCV 3/4's writer and EasyMocap's; numbers
are written with 17 significant digits (EasyMocap's writer keeps 6 decimals only).

aniposelib (``CameraGroup.load``): one TOML table per camera, keys ``name``, ``size`` ([width, height]),
``matrix`` (3x3), ``distortions`` (plural), ``rotation`` (Rodrigues), ``translation``, optional ``fisheye``,
and a ``[metadata]`` table. ``load`` orders cameras by *sorted table name*, so tables are ``cam_0``... with
the index zero-padded when there are ten cameras or more (``cam_10`` would sort before ``cam_2``).
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.image_files import read_image
from rigsfm.core.io import write_bytes_atomic, write_text_atomic
from rigsfm.core.names import ImageName

logger = logging.getLogger(__name__)

_PINHOLE_LIKE = {
    # COLMAP model -> OpenCV distortion from COLMAP's extra parameters (those after f/fx, fy, cx, cy)
    "SIMPLE_PINHOLE": lambda e: [0.0, 0.0, 0.0, 0.0, 0.0],
    "PINHOLE": lambda e: [0.0, 0.0, 0.0, 0.0, 0.0],
    "SIMPLE_RADIAL": lambda e: [e[0], 0.0, 0.0, 0.0, 0.0],
    "RADIAL": lambda e: [e[0], e[1], 0.0, 0.0, 0.0],
    "OPENCV": lambda e: [e[0], e[1], e[2], e[3], 0.0],
    "FULL_OPENCV": lambda e: list(e[:8]),  # k1 k2 p1 p2 k3 k4 k5 k6: OpenCV's rational model, same order
}
_FISHEYE = {
    "OPENCV_FISHEYE": lambda e: list(e[:4]),
    "SIMPLE_RADIAL_FISHEYE": lambda e: [e[0], 0.0, 0.0, 0.0],
    "RADIAL_FISHEYE": lambda e: [e[0], e[1], 0.0, 0.0],
}
SENSORS = ("wide", "narrow")


@dataclass(frozen=True)
class OpenCVCamera:
    """One camera in OpenCV's conventions."""

    name: str
    width: int
    height: int
    matrix: np.ndarray  # 3x3, OpenCV pixels
    distortion: np.ndarray  # OpenCV order (module docstring)
    fisheye: bool
    rvec: np.ndarray  # Rodrigues of cam_from_world's rotation
    tvec: np.ndarray  # cam_from_world's translation
    rotation: np.ndarray  # 3x3


def opencv_intrinsics(camera: pycolmap.Camera, where: str = "") -> tuple[np.ndarray, np.ndarray, bool]:
    """(K with OpenCV pixel centres, distortion in OpenCV's order, fisheye?) of a COLMAP camera; raises
    ``InputError`` for models OpenCV cannot express."""
    model = camera.model.name
    params = np.asarray(camera.params, dtype=np.float64)
    if model not in _PINHOLE_LIKE and model not in _FISHEYE:
        raise InputError(f"{where or 'camera'}: COLMAP model {model} has no OpenCV equivalent; use one of "
                         f"{', '.join([*_PINHOLE_LIKE, *_FISHEYE])} in rigs.yaml to export OpenCV cameras")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE"):
        fx = fy = params[0]
        cx, cy, extra = params[1], params[2], params[3:]
    else:
        fx, fy, cx, cy, extra = params[0], params[1], params[2], params[3], params[4:]
    k = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
    fisheye = model in _FISHEYE
    distortion = (_FISHEYE if fisheye else _PINHOLE_LIKE)[model](extra)
    return k, np.asarray(distortion, dtype=np.float64), fisheye


def _mean_pose(poses: Sequence[pycolmap.Rigid3d]) -> tuple[pycolmap.Rigid3d, float, float]:
    """The mean of a camera's frames' poses, and how far the frames' centres (model units) and rotations (deg)
    stray from it."""
    if len(poses) == 1:
        return poses[0], 0.0, 0.0
    quats = np.array([p.rotation.quat for p in poses])  # [x, y, z, w]
    quats *= np.sign(quats @ quats[0])[:, None]
    _, vectors = np.linalg.eigh(quats.T @ quats)
    mean_rotation = pycolmap.Rotation3d(vectors[:, -1] / np.linalg.norm(vectors[:, -1]))
    centres = np.array([p.inverse().translation for p in poses])
    centre = centres.mean(axis=0)
    spread_m = float(np.linalg.norm(centres - centre, axis=1).max())
    spread_deg = max(float(np.degrees((mean_rotation.inverse() * p.rotation).angle())) for p in poses)
    rotation = mean_rotation.matrix()
    return pycolmap.Rigid3d(mean_rotation, -rotation @ centre), spread_m, spread_deg


def _parsed(image_name: str) -> ImageName | None:
    try:
        return ImageName.parse(image_name)
    except ValueError:
        return None


def camera_name(image_name: str, camera_id: int) -> str:
    parsed = _parsed(image_name)
    raw = f"{parsed.rig}_{parsed.sensor}" if parsed else f"camera{camera_id}"
    return re.sub(r"[^A-Za-z0-9_-]", "_", raw)


def opencv_cameras(reconstruction: pycolmap.Reconstruction, sensors: Sequence[str] = SENSORS,
                   *, allow_fisheye: bool = True) -> list[OpenCVCamera]:
    """Every registered COLMAP camera of ``sensors`` (``<rig>/<sensor>/...`` image names; all cameras when the
    names do not follow that layout) in OpenCV's conventions, sorted by name."""
    by_camera: dict[int, list[pycolmap.Image]] = {}
    for image in reconstruction.images.values():
        parsed = _parsed(image.name)
        if image.has_pose and (parsed is None or str(parsed.sensor) in sensors):
            by_camera.setdefault(image.camera_id, []).append(image)
    cameras, strays = [], []
    for camera_id, images in by_camera.items():
        images.sort(key=lambda im: im.name)
        name = camera_name(images[0].name, camera_id)
        camera = reconstruction.cameras[camera_id]
        k, distortion, fisheye = opencv_intrinsics(camera, name)
        if fisheye and not allow_fisheye:
            raise InputError(f"{name}: {camera.model.name} is a fisheye model, which EasyMocap's intri.yml cannot "
                             "express (its reader always uses the pinhole model); export --format toml "
                             "(aniposelib reads fisheye cameras) or calibrate with OPENCV/FULL_OPENCV")
        pose, spread, spread_deg = _mean_pose([im.cam_from_world() for im in images])
        if spread > 1e-3 or spread_deg > 0.01:
            strays.append((spread, spread_deg, name, len(images)))
        rotation = pose.rotation.matrix()
        rvec, _ = cv2.Rodrigues(rotation)
        cameras.append(OpenCVCamera(name, int(camera.width), int(camera.height), k, distortion, fisheye,
                                    rvec.reshape(3), np.asarray(pose.translation, dtype=np.float64), rotation))
    if strays:  # one line for a recording's every camera: each frame is registered on its own
        largest = max(strays)
        logger.warning("%d camera(s) have several frames whose poses differ (up to %.3g in the model's units, metres "
                       "where the run is metric, and %.3g deg: %s, %d frames); each is exported as the mean of its "
                       "frames. Each frame is registered on its own, so static rigs differ by its noise (millimetres "
                       "at tens of metres); where a rig moved, `rigsfm track` says when", len(strays), largest[0],
                       max(s[1] for s in strays), largest[2], largest[3])
    cameras.sort(key=lambda c: c.name)
    names = [c.name for c in cameras]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise InputError(f"camera names {', '.join(repeated)} repeat after replacing characters OpenCV refuses; "
                         "rename the rigs (letters, digits, '_' and '-')")
    if not cameras:
        raise InputError(f"no registered camera of sensors {', '.join(sensors)} to export")
    return cameras


# --- EasyMocap / OpenCV FileStorage YAML ------------------------------------------------------------------


def _num(value: float) -> str:
    return repr(float(value))


def _yaml_matrix(key: str, value: np.ndarray) -> str:
    value = np.atleast_2d(np.asarray(value, dtype=np.float64))
    data = ", ".join(_num(v) for v in value.ravel())
    return f"{key}: !!opencv-matrix\n   rows: {value.shape[0]}\n   cols: {value.shape[1]}\n   dt: d\n   data: [ {data} ]\n"


def _yaml_names(names: Sequence[str]) -> str:
    return "names:\n" + "".join(f'   - "{n}"\n' for n in names)


def write_opencv(reconstruction: pycolmap.Reconstruction, dest: Path, sensors: Sequence[str] = SENSORS) -> list[Path]:
    """Write ``dest/intri.yml`` and ``dest/extri.yml`` (EasyMocap's layout, OpenCV FileStorage YAML)."""
    cameras = opencv_cameras(reconstruction, sensors, allow_fisheye=False)
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    header = "%YAML:1.0\n---\n"
    intri = header + _yaml_names([c.name for c in cameras])
    extri = header + _yaml_names([c.name for c in cameras])
    for c in cameras:
        intri += _yaml_matrix(f"K_{c.name}", c.matrix)
        intri += _yaml_matrix(f"dist_{c.name}", c.distortion.reshape(1, -1))
        intri += f"H_{c.name}: {c.height}\nW_{c.name}: {c.width}\n"
        extri += _yaml_matrix(f"R_{c.name}", c.rvec.reshape(3, 1))
        extri += _yaml_matrix(f"Rot_{c.name}", c.rotation)
        extri += _yaml_matrix(f"T_{c.name}", c.tvec.reshape(3, 1))
    paths = [dest / "intri.yml", dest / "extri.yml"]
    write_text_atomic(paths[0], intri)
    write_text_atomic(paths[1], extri)
    return paths


# --- aniposelib TOML --------------------------------------------------------------------------------------


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not np.isfinite(v):
            raise ValueError(f"cannot write {v} to a camera file")
        return repr(v)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=True)  # a valid TOML basic string
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return "[ " + ", ".join(_toml_value(v) for v in value) + " ]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def write_toml(reconstruction: pycolmap.Reconstruction, dest: Path, sensors: Sequence[str] = SENSORS,
               metadata: dict[str, str] | None = None) -> list[Path]:
    """Write ``dest/calibration.toml`` (aniposelib's ``CameraGroup.dump`` layout)."""
    cameras = opencv_cameras(reconstruction, sensors, allow_fisheye=True)
    width = len(str(len(cameras) - 1))
    lines = []
    for index, c in enumerate(cameras):
        lines.append(f"[cam_{index:0{width}d}]")
        entries: dict[str, object] = {"name": c.name, "size": [c.width, c.height], "matrix": c.matrix,
                                      "distortions": c.distortion, "rotation": c.rvec, "translation": c.tvec}
        if c.fisheye:
            entries["fisheye"] = True
        lines += [f"{key} = {_toml_value(value)}" for key, value in entries.items()]
        lines.append("")
    meta = {"source": "rigsfm", "pixels": "OpenCV: first pixel centre at (0, 0)",
            "pose": "rotation (Rodrigues), translation: x_cam = R x_world + t, reconstruction world units",
            **(metadata or {})}
    lines.append("[metadata]")
    lines += [f"{key} = {_toml_value(str(value))}" for key, value in meta.items()]
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    path = dest / "calibration.toml"
    write_text_atomic(path, "\n".join(lines) + "\n")
    return [path]


# --- WILDTRACK / MVDet ------------------------------------------------------------------------------------


def _xml_matrix(key: str, value: np.ndarray) -> str:
    value = np.atleast_2d(np.asarray(value, dtype=np.float64))
    data = " ".join(_num(v) for v in value.ravel())
    return (f'<{key} type_id="opencv-matrix">\n  <rows>{value.shape[0]}</rows>\n  <cols>{value.shape[1]}</cols>\n'
            f"  <dt>d</dt>\n  <data>\n    {data}</data></{key}>\n")


def write_wildtrack(reconstruction: pycolmap.Reconstruction, dest: Path, images_dir: Path | None = None, *,
                    lent: Mapping[str, pycolmap.Image] | None = None) -> list[Path]:
    """WILDTRACK's calibration layout, as MVDet-family loaders read it, for the narrow cameras:
    ``calibrations/intrinsic_zero/intr_<rig>.xml`` (OpenCV FileStorage XML: ``camera_matrix`` with OpenCV pixel
    centres and zero ``distortion_coefficients``: for undistorted images) and ``calibrations/extrinsic/
    extr_<rig>.xml`` (``<rvec>`` Rodrigues and ``<tvec>`` in centimetres, world-to-camera, as space-separated text
    the loaders split). World: the run's, in centimetres; in the floor frame the floor is z = 0, the plane MVDet
    projects onto. With ``images_dir``: ``Image_subsets/<rig>/<frame>.png``, each narrow image undistorted to that
    camera matrix; ``lent``: more narrow image names under ``images_dir`` (frames the run was not given), each
    undistorted as the run's image it maps to (its camera: static rigs)."""
    cameras = opencv_cameras(reconstruction, ("narrow",), allow_fisheye=False)
    dest = Path(dest)
    intrinsic, extrinsic = dest / "calibrations" / "intrinsic_zero", dest / "calibrations" / "extrinsic"
    intrinsic.mkdir(parents=True, exist_ok=True)
    extrinsic.mkdir(parents=True, exist_ok=True)
    paths = []
    for c in cameras:
        rig = c.name.removesuffix("_narrow")
        text = ('<?xml version="1.0"?>\n<opencv_storage>\n' + _xml_matrix("camera_matrix", c.matrix)
                + _xml_matrix("distortion_coefficients", np.zeros((1, 5))) + "</opencv_storage>\n")
        paths.append(write_text_atomic(intrinsic / f"intr_{rig}.xml", text))
        text = ('<?xml version="1.0"?>\n<opencv_storage>\n'
                f"<rvec>{' '.join(_num(v) for v in c.rvec)}</rvec>\n"
                f"<tvec>{' '.join(_num(100.0 * v) for v in c.tvec)}</tvec>\n</opencv_storage>\n")
        paths.append(write_text_atomic(extrinsic / f"extr_{rig}.xml", text))
    if images_dir is not None:
        paths += _undistorted_images(reconstruction, cameras, dest / "Image_subsets", Path(images_dir), lent or {})
    return paths


def _undistorted_images(reconstruction: pycolmap.Reconstruction, cameras: Sequence[OpenCVCamera], dest: Path,
                        images_dir: Path, lent: Mapping[str, pycolmap.Image]) -> list[Path]:
    by_name = {c.name: c for c in cameras}
    paths = []
    maps: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    own = [(image.name, image) for image in reconstruction.images.values()]
    for name, image in sorted([*own, *lent.items()], key=lambda item: item[0]):
        parsed = _parsed(name)
        if not image.has_pose or parsed is None or not parsed.is_narrow:
            continue
        c = by_name.get(camera_name(image.name, image.camera_id))
        if c is None:
            continue
        source = images_dir / name
        pixels = read_image(source, cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise InputError(f"cannot read {source} to undistort it; export without images or restore the file")
        if pixels.shape[:2] != (c.height, c.width):  # a lent frame's picture from another camera or setting
            raise InputError(f"{source} is {pixels.shape[1]}x{pixels.shape[0]} px, its camera {c.name} "
                             f"{c.width}x{c.height}: export it without --poses-from or replace the file")
        if c.name not in maps:
            maps[c.name] = cv2.initUndistortRectifyMap(c.matrix, c.distortion, None, c.matrix, (c.width, c.height),
                                                       cv2.CV_32FC1)
        undistorted = cv2.remap(pixels, *maps[c.name], cv2.INTER_LINEAR)
        # the camera's name, as its calibration files are named (a rig named with a space: rig_01, not 'rig 01')
        target = dest / c.name.removesuffix("_narrow") / (Path(parsed.frame).stem + ".png")
        target.parent.mkdir(parents=True, exist_ok=True)
        ok, data = cv2.imencode(".png", undistorted)
        if not ok:
            raise OSError(f"could not encode {target}")
        paths.append(write_bytes_atomic(target, data.tobytes()))
    _warn_missing_views(paths, dest)
    return paths


def _warn_missing_views(paths: list[Path], dest: Path) -> None:
    """One warning where a camera lacks a frame the others have (its narrow image was not registered or not given):
    multi-view detectors read every camera in every frame.

    Not ``rigsfm.run.inputs.images.rigs_missing_frames``, though alike: that one reads the images given (wide, every
    rig of rigs.yaml, a rig with none lacking all) and names a frame only a minority of rigs has as that rig's extra
    file; this one reads the narrow images exported (registered ones, only the cameras written), where any frame not
    in every camera, however many have it, is one a loader cannot read."""
    frames: dict[str, set[str]] = {}
    for path in paths:
        frames.setdefault(path.parent.name, set()).add(path.name)
    every = set().union(*frames.values()) if frames else set()
    missing = {rig: sorted(every - have) for rig, have in sorted(frames.items()) if every - have}
    if missing:
        first = next(iter(missing))
        logger.warning("%s: %d camera(s) lack frames the others have (%s: %s%s): the run has no registered narrow image "
                       "there; loaders of the MVDet family expect every camera in every frame, so leave those frames "
                       "out of the dataset or give the run their images", dest, len(missing), first,
                       ", ".join(missing[first][:3]), ", ..." if len(missing[first]) > 3 else "")
