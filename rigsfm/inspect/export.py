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

import json
import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.conventions import CONVENTIONS, opengl_c2w_from_cam_from_world
from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.io import file_sha256, write_json_atomic
from rigsfm.core.names import name_of
from rigsfm.core.owned import Previous, commit, previous_files
from rigsfm.core.serialise import camera_to_dict, pose_to_dict
from rigsfm.core.summary import Summary
from rigsfm.core.workspace import Workspace, model_fingerprint
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
    if len(scene.points.points) == 0:  # Open3D neither writes nor reads a cloud of no points
        logger.warning("the model holds no 3D points: the Open3D export has the cameras only (no points.ply)")
    elif not o3d.io.write_point_cloud(str(dest / "points.ply"), scene.points):  # type: ignore[arg-type]  # takes str
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
    frames, missing = [], []
    for image in registered_images(reconstruction):
        path = (images_dir / image.name).resolve() if images_dir is not None else Path(image.name)
        if images_dir is None or not path.is_file():
            missing.append(image.name)
        frames.append({"file_path": str(path), **nerfstudio_intrinsics(reconstruction.cameras[image.camera_id]),
                       "transform_matrix": opengl_c2w_from_cam_from_world(image.cam_from_world()).tolist(),
                       "rigsfm_name": image.name})
    if missing:  # nerfstudio loads every file_path before it trains: say so now, not there
        where = (f"the run's image folder {images_dir} lacks" if images_dir is not None else
                 "summary.json names no image folder, so file_path is the bare image name for")
        logger.warning("nerfstudio export: %s %d of %d image(s) (%s%s); nerfstudio will not find them: put the run's "
                       "images back (or edit file_path) before training", where, len(missing), len(frames),
                       ", ".join(missing[:3]), " ..." if len(missing) > 3 else "")
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


def write_json_poses(reconstruction: pycolmap.Reconstruction, dest: Path, result: dict | None = None) -> list[Path]:
    """``poses.json``; ``result``: the run's ``metric``, ``units`` and ``world`` (from narrow_poses.json), which say
    what the numbers are in."""
    images = []
    for image in registered_images(reconstruction):
        name = name_of(image)
        images.append({"name": image.name, "rig": name.rig, "sensor": str(name.sensor), "frame": name.frame,
                       "camera": camera_to_dict(reconstruction.cameras[image.camera_id]),
                       "cam_from_world": pose_to_dict(image.cam_from_world()),
                       "centre": image.projection_center().tolist()})
    write_json_atomic(dest / "poses.json", {**(result or {}),
                                            "conventions": {k: CONVENTIONS[k] for k in
                                                            ("cam_from_world", "quaternion", "pixels")},
                                            "images": images})
    return sorted(dest.iterdir())


def read_narrow_poses(workspace: Workspace) -> dict | None:
    """narrow_poses.json (read once per export: its ``metric`` and ``world`` say what the numbers are in), None
    where it cannot be read."""
    try:
        poses = json.loads(workspace.narrow_poses.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    return poses if isinstance(poses, dict) else None


def result_frame(poses: dict | None) -> dict:
    """narrow_poses.json's (``poses``) ``metric``, ``units`` and ``world``: what the poses' numbers are in."""
    return {key: poses[key] for key in ("metric", "units", "world") if key in poses} if poses else {}


def world_metadata(poses: dict | None) -> dict[str, str]:
    """The run's world frame in words, for the files' metadata (from narrow_poses.json, ``poses``)."""
    world = (poses or {}).get("world") or {}
    if world.get("frame") == "floor":
        return {"world": f"floor frame: z {world.get('z_axis')}; origin {world.get('origin')}; "
                         f"x {world.get('x_axis')}", "units": str(world.get("units", "metres"))}
    return {"world": "the mapper's frame (no floor frame)"} if world else {}


def warn_wildtrack_world(poses: dict | None) -> None:
    """WILDTRACK's loaders take the extrinsics in centimetres with the floor at z = 0: say where the run's world
    (narrow_poses.json, ``poses``) is neither (the files carry no units or frame to tell them)."""
    if poses is None:
        return
    problems = []
    if poses.get("metric") is not True:
        problems.append("not metric (its units are arbitrary, written as if metres x 100)")
    if (poses.get("world") or {}).get("frame") != "floor":
        problems.append("not in the floor frame (z = 0 is not the floor that WILDTRACK/MVDet project onto)")
    if problems:
        logger.warning("WILDTRACK export of a result %s: a loader will take it for centimetres on the floor",
                       " and ".join(problems))


def warn_not_metric(workspace: Workspace, poses: dict | None, fmt: ExportFormat) -> None:
    """Say where the run's result (narrow_poses.json, ``poses``) has no scale: every format but COLMAP's is read as
    metres by its tools (the files carry no units), and the docs promise metres (WILDTRACK's own warning says
    centimetres)."""
    if poses is not None and poses.get("metric") is False:
        logger.warning("NOT METRIC: %s has no scale, so the %s export's positions are in the mapper's arbitrary unit, "
                       "which its readers take for metres; give `rigsfm run` a scale.yaml (a camera distance or a "
                       "known length) for metres", workspace.root, fmt)


def warn_changed_images(workspace: Workspace, reconstruction: pycolmap.Reconstruction, images_dir: Path) -> None:
    """Say which narrow images now hold other pictures than the run was made from (images.json): their undistorted
    copies pair new pixels with the run's calibration."""
    from rigsfm.run.matching.reuse import recorded_contents

    recorded = recorded_contents(workspace.image_contents)
    changed = []
    for image in registered_images(reconstruction):
        path = images_dir / image.name
        if name_of(image).is_narrow and image.name in recorded and path.is_file() \
                and file_sha256(path) != recorded[image.name]:
            changed.append(image.name)
    if changed:
        logger.warning("%d narrow image(s) changed since the run (%s%s): their undistorted copies show the new pictures "
                       "with the run's calibration; where the rigs may have moved, re-run `rigsfm run --overwrite` on "
                       "them first", len(changed), ", ".join(changed[:3]), " ..." if len(changed) > 3 else "")


def frames_not_in_run(reconstruction: pycolmap.Reconstruction, images_dir: Path) -> list[str]:
    """The narrow images in ``images_dir`` (``<rig>/narrow/<frame file>``) of the run's registered narrow cameras
    that the run does not hold: a recording put beside its images (``rigsfm associate --poses-from``)."""
    from rigsfm.run.inputs.images import IMAGE_SUFFIXES

    held = {image.name for image in reconstruction.images.values()}
    rigs = {name_of(image).rig for image in registered_images(reconstruction) if name_of(image).is_narrow}
    names = []
    for rig in sorted(rigs):
        try:
            files = sorted(p.name for p in (images_dir / rig / "narrow").iterdir()
                           if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        except OSError:
            continue  # the folder is gone: the run's own images are refused by name when read
        names += [f"{rig}/narrow/{file}" for file in files if f"{rig}/narrow/{file}" not in held]
    return names


def lent_images(reconstruction: pycolmap.Reconstruction, images_dir: Path, poses_from: str | None
                ) -> dict[str, pycolmap.Image]:
    """Per narrow image of ``images_dir`` the run was not given (:func:`frames_not_in_run`), the run's narrow image
    of its camera in frame ``poses_from`` (static rigs: the same camera); without ``poses_from``, none, and a
    warning naming the frames left out."""
    names = frames_not_in_run(reconstruction, images_dir)
    frames = sorted({name.rsplit("/", 1)[1] for name in names})
    if poses_from is None:
        if names:
            own = sorted({name_of(im).frame for im in registered_images(reconstruction) if name_of(im).is_narrow})
            logger.warning("%d narrow image(s) of %d frame(s) the run was not given (%s%s) lie beside its images in "
                           "%s and are not exported: pass --poses-from %s (a frame of the run) to write them "
                           "undistorted with its cameras (static rigs; `rigsfm track` tells whether a rig moved)",
                           len(names), len(frames), ", ".join(frames[:3]), " ..." if len(frames) > 3 else "",
                           images_dir, own[0] if own else "FRAME")
        return {}
    reference = {name_of(im).rig: im for im in registered_images(reconstruction)
                 if name_of(im).is_narrow and name_of(im).frame == poses_from}
    if not reference:
        own = sorted({name_of(im).frame for im in registered_images(reconstruction) if name_of(im).is_narrow})
        raise InputError(f"--poses-from {poses_from!r} is not a frame of this run with a registered narrow image; its "
                         f"frames: {', '.join(own[:8])}{' ...' if len(own) > 8 else ''}")
    lent = {name: reference[name.split("/", 1)[0]] for name in names if name.split("/", 1)[0] in reference}
    if names and len(lent) < len(names):
        left = sorted({name.split("/", 1)[0] for name in names} - set(reference))
        logger.warning("frame %s of the run has no registered narrow image of %s: their images of the frames the run "
                       "was not given are not exported", poses_from, ", ".join(left))
    return lent


def check_destination(dest: Path, workspace: Workspace, *, overwrite: bool) -> Previous:
    """What an export into ``dest`` may replace: the files of an earlier export listed in its manifest and still
    as rigsfm wrote them.

    Refuses the workspace itself or a folder that holds it, a folder with files no manifest lists, and an earlier
    export without ``overwrite``."""
    if workspace.is_within(dest):
        raise WorkspaceError(f"--dest '{dest}' is the workspace or a folder that holds it; choose a folder of its own "
                             f"(the default is {workspace.export('FORMAT')})")
    resolved, exports = dest.resolve(), workspace.exports.resolve()
    if resolved.is_relative_to(workspace.root.resolve()) and not resolved.is_relative_to(exports):
        raise WorkspaceError(f"--dest '{dest}' is inside the workspace's own files; use {exports}/... or a folder "
                             "outside the workspace")
    return previous_files(dest, MANIFEST, overwrite=overwrite, option="--dest", what="export")


def export(out: Path, options: ExportOptions) -> Path:
    """Write the workspace's result in ``options.format`` into ``options.dest`` (default ``OUT/export/<format>``)
    and return that folder. Only an earlier export's own files, unchanged since, are ever replaced (see
    ``check_destination``)."""
    workspace = Workspace(Path(out))
    workspace.require_result()
    workspace.warn_unfinished()
    fmt = ExportFormat(options.format)
    if options.images and fmt != ExportFormat.WILDTRACK:  # refused rather than ignored: the user asked for images
        raise InputError(f"--images writes the undistorted narrow images of --format wildtrack only; export "
                         f"{fmt} without it")
    if options.poses_from is not None and not options.images:
        raise InputError("--poses-from needs --images (--format wildtrack): it lends the run's cameras to the narrow "
                         "images of frames the run was not given")
    with workspace.reading():  # a run rewriting the model now is refused, not exported half old, half new
        return _export(workspace, fmt, options)


def _export(workspace: Workspace, fmt: ExportFormat, options: ExportOptions) -> Path:
    dest = Path(options.dest) if options.dest is not None else workspace.export(fmt)
    previous = check_destination(dest, workspace, overwrite=options.overwrite)
    reconstruction = workspace.read_sparse()
    summary = Summary.read(workspace.summary)
    images_dir = Path(summary.inputs.images) if summary and summary.inputs.images else None
    if options.images and images_dir is None:
        raise InputError(f"{workspace.summary} names no image folder; export without --images" if summary else
                         f"{workspace.summary} is missing (the run stopped before writing it), so the run's image "
                         "folder is unknown: re-run the same `rigsfm run` command to finish it, or export without "
                         "--images")
    workspace.refuse_among_images(dest, f"--dest '{dest}'",
                                  f"choose a folder outside it (the default is {workspace.export(fmt)})")
    poses = read_narrow_poses(workspace)
    if fmt not in (ExportFormat.COLMAP_BIN, ExportFormat.COLMAP_TXT, ExportFormat.WILDTRACK):  # (COLMAP: no units)
        warn_not_metric(workspace, poses, fmt)
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
            write_toml(reconstruction, tmp, metadata=world_metadata(poses))
        elif fmt == ExportFormat.WILDTRACK:
            warn_wildtrack_world(poses)
            lent: dict[str, pycolmap.Image] = {}
            if options.images and images_dir is not None:
                warn_changed_images(workspace, reconstruction, images_dir)
                lent = lent_images(reconstruction, images_dir, options.poses_from)
            write_wildtrack(reconstruction, tmp, images_dir if options.images else None, lent=lent)
        else:
            write_json_poses(reconstruction, tmp, result_frame(poses))
        commit(dest, tmp, previous, MANIFEST, {"format": str(fmt), "workspace": str(workspace.root.resolve()),
                                             "model": model_fingerprint(workspace.sparse)},
               option="--dest", what="export")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # the temporary folder made above: only rigsfm's files
    logger.info("Exported %s to %s", fmt, dest)
    return dest
