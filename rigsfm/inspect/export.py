"""``rigsfm export OUT --format ...``: the result in the formats other tools read.

- ``colmap-bin`` / ``colmap-txt``: the COLMAP model (pycolmap's writer; rigs.* and frames.* are ignored by
  COLMAP < 3.12, which still reads cameras, images and points). Pixels: COLMAP (first centre at 0.5).
- ``open3d``: ``points.ply`` (PointCloud), ``frustums.ply`` (LineSet: wide blue, narrow orange, rig links
  green), ``trajectory.json`` (``PinholeCameraTrajectory``: per image, pinhole intrinsics with OpenCV pixel
  centres, i.e. COLMAP cx - 0.5, distortion dropped, and extrinsic = cam_from_world, OpenCV axes) and
  ``cameras.json`` (which image each trajectory entry is).
- ``nerfstudio``: ``transforms.json`` with per-frame OPENCV intrinsics (fl_x, fl_y, cx, cy, w, h, k1, k2,
  p1, p2; nerfstudio puts pixel centres at +0.5 like COLMAP, so cx/cy are COLMAP's unchanged) and
  ``transform_matrix`` = camera-to-world with OpenGL axes; the world is rigsfm's metric world
  (``applied_transform`` identity); ``points3D.ply`` as ``ply_file_path``.
- ``json``: ``poses.json``, every registered image's camera (COLMAP convention) and cam_from_world.
- ``opencv``: ``intri.yml`` / ``extri.yml`` (OpenCV FileStorage YAML, EasyMocap's layout) and ``toml``:
  ``calibration.toml`` (aniposelib's ``CameraGroup`` layout): one entry per camera (``<rig>_<sensor>``), K and
  distortion with OpenCV pixel centres (cx = COLMAP cx - 0.5), R (Rodrigues) and t world-to-camera in metres,
  image size (``rigsfm.inspect.camera_files``). The world is the run's (the floor frame by default).
- ``wildtrack``: ``calibrations/intrinsic_zero/intr_<rig>.xml`` and ``calibrations/extrinsic/extr_<rig>.xml`` of
  the narrow cameras, WILDTRACK's layout as MVDet-family loaders read it (centimetres, undistorted images), and
  with ``images`` the undistorted narrow images (``Image_subsets/<rig>/<frame>.png``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.conventions import CONVENTIONS, opengl_c2w_from_cam_from_world
from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.io import sha256_file, write_json_atomic
from rigsfm.core.names import name_of
from rigsfm.core.serialise import camera_to_dict, pose_to_dict
from rigsfm.core.summary import Summary
from rigsfm.core.workspace import Workspace
from rigsfm.inspect.camera_files import write_opencv, write_toml, write_wildtrack
from rigsfm.inspect.options import ExportFormat, ExportOptions

logger = logging.getLogger(__name__)

MANIFEST = ".rigsfm-export.json"  # the files rigsfm wrote into an export folder and their SHA-256: all --overwrite may remove


def registered_images(reconstruction: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    return sorted((im for im in reconstruction.images.values() if im.has_pose), key=lambda im: im.name)


def write_colmap(reconstruction: pycolmap.Reconstruction, dest: Path, *, binary: bool) -> list[Path]:
    if binary:
        reconstruction.write_binary(str(dest))
    else:
        reconstruction.write_text(str(dest))
    return sorted(dest.iterdir())


def write_open3d(reconstruction: pycolmap.Reconstruction, dest: Path) -> list[Path]:
    import open3d as o3d

    from rigsfm.inspect.viewer import build_scene, pinhole_intrinsic

    scene = build_scene(reconstruction)
    if not o3d.io.write_point_cloud(str(dest / "points.ply"), scene.points):  # type: ignore[arg-type]  # takes str too
        raise WorkspaceError(f"Open3D could not write {dest / 'points.ply'}")
    frustums = o3d.geometry.LineSet()
    for line_set in scene.lines.values():
        frustums += line_set
    if not o3d.io.write_line_set(str(dest / "frustums.ply"), frustums):  # type: ignore[arg-type]  # takes str too
        raise WorkspaceError(f"Open3D could not write {dest / 'frustums.ply'}")
    trajectory = o3d.camera.PinholeCameraTrajectory()
    parameters, names = [], []
    for image in registered_images(reconstruction):
        p = o3d.camera.PinholeCameraParameters()
        p.intrinsic = pinhole_intrinsic(reconstruction.cameras[image.camera_id])
        p.extrinsic = np.vstack([image.cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])
        parameters.append(p)
        names.append(image.name)
    trajectory.parameters = parameters
    # takes str too
    if not o3d.io.write_pinhole_camera_trajectory(str(dest / "trajectory.json"), trajectory):  # type: ignore[arg-type]
        raise WorkspaceError(f"Open3D could not write {dest / 'trajectory.json'}")
    write_json_atomic(dest / "cameras.json", {
        "trajectory_entries": names,
        "conventions": {"intrinsic": "pinhole part only (distortion dropped), OpenCV pixel centres: cx = COLMAP cx - 0.5",
                        "extrinsic": "cam_from_world (world to camera), OpenCV axes, metres"}})
    return sorted(dest.iterdir())


def nerfstudio_intrinsics(camera: pycolmap.Camera) -> dict:
    """Per-frame OPENCV intrinsics; pixel centres as in COLMAP (nerfstudio also offsets pixels by 0.5)."""
    names = [n.strip() for n in camera.params_info.split(",")]
    values = dict(zip(names, (float(v) for v in camera.params)))
    supported = {"f", "fx", "fy", "cx", "cy", "k", "k1", "k2", "p1", "p2"}
    if not set(names) <= supported:
        raise InputError(f"camera model {camera.model.name} cannot be written as nerfstudio OPENCV "
                         f"({', '.join(sorted(set(names) - supported))} unsupported)")
    return {
        "camera_model": "OPENCV",
        "fl_x": values.get("fx", values.get("f")), "fl_y": values.get("fy", values.get("f")),
        "cx": values["cx"], "cy": values["cy"], "w": int(camera.width), "h": int(camera.height),
        "k1": values.get("k1", values.get("k", 0.0)), "k2": values.get("k2", 0.0),
        "p1": values.get("p1", 0.0), "p2": values.get("p2", 0.0),
    }


def write_nerfstudio(reconstruction: pycolmap.Reconstruction, dest: Path, images_dir: Path | None) -> list[Path]:
    frames = []
    for image in registered_images(reconstruction):
        path = (images_dir / image.name).resolve() if images_dir is not None else Path(image.name)
        frames.append({"file_path": str(path), **nerfstudio_intrinsics(reconstruction.cameras[image.camera_id]),
                       "transform_matrix": opengl_c2w_from_cam_from_world(image.cam_from_world()).tolist(),
                       "rigsfm_name": image.name})
    reconstruction.export_PLY(str(dest / "points3D.ply"))
    write_json_atomic(dest / "transforms.json", {
        "frames": frames,
        "ply_file_path": "points3D.ply",
        "applied_transform": np.eye(4)[:3].tolist(),
        "rigsfm_conventions": {
            "transform_matrix": "camera-to-world, OpenGL camera axes (x right, y up, looking down -z), metres",
            "applied_transform": "identity: the world is rigsfm's (COLMAP model) world, not re-oriented",
            "pixels": "COLMAP/nerfstudio: centre of the first pixel at (0.5, 0.5); cx, cy unchanged",
            "file_path": "absolute path of the image in the run's images folder" if images_dir else "image name",
        }})
    return sorted(dest.iterdir())


def write_json_poses(reconstruction: pycolmap.Reconstruction, dest: Path) -> list[Path]:
    images = []
    for image in registered_images(reconstruction):
        name = name_of(image)
        images.append({"name": image.name, "rig": name.rig, "sensor": str(name.sensor), "frame": name.frame,
                       "camera": camera_to_dict(reconstruction.cameras[image.camera_id]),
                       "cam_from_world": pose_to_dict(image.cam_from_world()),
                       "centre": image.projection_center().tolist()})
    write_json_atomic(dest / "poses.json", {"conventions": {k: CONVENTIONS[k] for k in
                                                            ("cam_from_world", "quaternion", "pixels")},
                                            "images": images})
    return sorted(dest.iterdir())


def world_metadata(workspace: Workspace) -> dict[str, str]:
    """The run's world frame in words, for the files' metadata (from narrow_poses.json)."""
    try:
        world = json.loads(workspace.narrow_poses.read_text(encoding="utf-8")).get("world") or {}
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        world = {}
    if world.get("frame") == "floor":
        return {"world": f"floor frame: z {world.get('z_axis')}; origin {world.get('origin')}; "
                         f"x {world.get('x_axis')}", "units": str(world.get("units", "metres"))}
    return {"world": "the mapper's frame (no floor frame)"} if world else {}


@dataclass(frozen=True)
class Previous:
    """An earlier export in DEST, by its manifest: ``ours`` are files still as rigsfm wrote them (their checksum
    matches), ``changed`` listed files that are not (edited, replaced, no checksum, not a plain file), ``invalid``
    entries that name no file of DEST (absolute, ``..``, a sub-folder): only ``ours`` are ever removed."""

    ours: tuple[str, ...] = ()
    changed: tuple[str, ...] = ()
    invalid: tuple[str, ...] = ()


def _is_plain_name(name: object) -> bool:
    """A file inside DEST: a relative POSIX path without ``.`` or ``..`` parts, not the manifest itself."""
    return (isinstance(name, str) and name != MANIFEST and "\\" not in name and "\0" not in name
            and not name.startswith("/") and all(part not in ("", ".", "..") for part in name.split("/")))


def _files_under(folder: Path) -> list[str]:
    """Every file (and link) below ``folder`` as a relative POSIX path; folders are not entries."""
    names = []
    for here, dirs, files in os.walk(folder):
        for name in [*files, *(d for d in dirs if os.path.islink(os.path.join(here, d)))]:
            names.append(Path(here, name).relative_to(folder).as_posix())
    return sorted(names)


def read_manifest(dest: Path) -> tuple[list[str], dict[str, str], list[str]]:
    """(listed plain names, their recorded SHA-256, entries that are not plain names) of DEST's manifest; nothing
    for a manifest that is missing, a link, or not one rigsfm writes."""
    manifest = dest / MANIFEST
    if manifest.is_symlink() or not manifest.is_file():
        return [], {}, []
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return [], {}, []
    files = data.get("files") if isinstance(data, dict) else None
    if not isinstance(files, list):
        return [], {}, []
    sums = data.get("sha256") if isinstance(data.get("sha256"), dict) else {}
    listed = [name for name in files if _is_plain_name(name)]
    invalid = [str(name) for name in files if not _is_plain_name(name)]
    return listed, {name: sums[name] for name in listed if isinstance(sums.get(name), str)}, invalid


def _still_ours(path: Path, checksum: str | None) -> bool:
    """Whether ``path`` is a plain file (not a link) whose content is what rigsfm recorded writing."""
    try:
        if checksum is None or not stat.S_ISREG(os.lstat(path).st_mode):
            return False
        return sha256_file(path) == checksum
    except OSError:
        return False


def check_destination(dest: Path, workspace: Workspace, *, overwrite: bool) -> Previous:
    """What an export into ``dest`` may replace: the files of an earlier export listed in its manifest and still
    as rigsfm wrote them.

    Refuses the workspace itself or a folder that holds it, a folder with files no manifest lists, and an earlier
    export without ``overwrite``."""
    resolved, root = dest.resolve(), workspace.root.resolve()
    if resolved == root or root.is_relative_to(resolved):
        raise WorkspaceError(f"--dest '{dest}' is the workspace or a folder that holds it; choose a folder of its own "
                             f"(the default is {workspace.export('FORMAT')})")
    if resolved.is_relative_to(root) and not resolved.is_relative_to(root / "export"):
        raise WorkspaceError(f"--dest '{dest}' is inside the workspace's own files; use {root / 'export'}/... or a folder "
                             "outside the workspace")
    if not dest.exists():
        return Previous()
    if not dest.is_dir():
        raise WorkspaceError(f"--dest {dest} exists and is not a folder; choose a new or empty folder")
    present = _files_under(dest)
    if not present:
        return Previous()
    listed, sums, invalid = read_manifest(dest)
    foreign = [name for name in present if name != MANIFEST and name not in listed]
    if foreign:
        raise WorkspaceError(f"--dest '{dest}' holds files rigsfm did not write ({', '.join(foreign[:3])}"
                             f"{', ...' if len(foreign) > 3 else ''}); choose a new or empty folder (nothing was "
                             "written or removed)")
    if not overwrite:
        raise WorkspaceError(f"{dest} already holds an export: pass --overwrite to replace it")
    there = [name for name in listed if os.path.lexists(dest / name)]
    ours = tuple(name for name in there if _still_ours(dest / name, sums.get(name)))
    return Previous(ours, tuple(name for name in there if name not in ours), tuple(invalid))


def _replace_previous(dest: Path, previous: Previous, written: list[str]) -> None:
    """Refuse to write over a listed file that is no longer rigsfm's; remove the earlier export's own files that
    this one does not write again (those it does are replaced by the rename); keep the others with a warning."""
    collide = [name for name in previous.changed if name in written]
    if collide:
        raise WorkspaceError(f"'{dest / collide[0]}' is not what an earlier export wrote there (edited or replaced "
                             "since); move it away or choose another --dest (nothing was written or removed)")
    for name in previous.changed:
        logger.warning("Kept %s: its content is not what rigsfm wrote there (edited or replaced since), so it is no "
                       "longer part of the export", dest / name)
    for name in previous.invalid:
        logger.warning("Ignored %r in %s: not a file of %s, so nothing was removed for it", name, dest / MANIFEST, dest)
    for name in previous.ours:
        if name not in written:
            (dest / name).unlink(missing_ok=True)
            folder = (dest / name).parent
            while folder != dest:  # the export's own sub-folders, once they are empty
                with contextlib.suppress(OSError):
                    folder.rmdir()
                folder = folder.parent


def export(out: Path, options: ExportOptions) -> Path:
    """Write the workspace's result in ``options.format`` into ``options.dest`` (default ``OUT/export/<format>``)
    and return that folder. Only an earlier export's own files, unchanged since, are ever replaced (see
    ``check_destination``)."""
    workspace = Workspace(Path(out))
    workspace.require_result()
    fmt = ExportFormat(options.format)
    dest = Path(options.dest) if options.dest is not None else workspace.export(fmt)
    previous = check_destination(dest, workspace, overwrite=options.overwrite)
    reconstruction = workspace.read_sparse()
    summary = Summary.read(workspace.summary)
    images_dir = Path(summary.inputs.images) if summary and summary.inputs.images else None
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    try:
        if fmt in (ExportFormat.COLMAP_BIN, ExportFormat.COLMAP_TXT):
            write_colmap(reconstruction, tmp, binary=fmt == ExportFormat.COLMAP_BIN)
        elif fmt == ExportFormat.OPEN3D:
            write_open3d(reconstruction, tmp)
        elif fmt == ExportFormat.NERFSTUDIO:
            write_nerfstudio(reconstruction, tmp, images_dir)
        elif fmt == ExportFormat.OPENCV:
            write_opencv(reconstruction, tmp)
        elif fmt == ExportFormat.TOML:
            write_toml(reconstruction, tmp, metadata=world_metadata(workspace))
        elif fmt == ExportFormat.WILDTRACK:
            if options.images and images_dir is None:
                raise InputError(f"{workspace.summary} names no image folder; export without --images")
            write_wildtrack(reconstruction, tmp, images_dir if options.images else None)
        else:
            write_json_poses(reconstruction, tmp)
        written = _files_under(tmp)
        write_json_atomic(tmp / MANIFEST, {"format": str(fmt), "workspace": str(workspace.root.resolve()),
                                            "files": written,
                                            "sha256": {name: sha256_file(tmp / name) for name in written}})
        dest.mkdir(exist_ok=True)
        _replace_previous(dest, previous, written)
        for name in [*written, MANIFEST]:
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / name, dest / name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # the temporary folder made above: only rigsfm's files
    logger.info("Exported %s to %s", fmt, dest)
    return dest
