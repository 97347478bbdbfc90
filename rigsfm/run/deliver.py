"""Stage 9, deliver: write the deliverables — COLMAP model, narrow_poses.json, points3D.ply.

``narrow_poses.json`` conventions (also in the file's ``conventions`` block):
- ``cam_from_world``: x_cam = R x_world + t, metres; ``centre`` = -R^T t, world frame.
- For each narrow pair (i, j): ``narrow_j_from_narrow_i`` maps camera-i coordinates to camera-j.
- ``euler_zyx_deg`` = (yaw, pitch, roll) with R = Rz(yaw) Ry(pitch) Rx(roll).
- ``centre_direction_in_i``: unit vector from camera i's centre to camera j's, in camera i's frame.
- ``F_ji``: x_j^T F_ji x_i = 0 for homogeneous COLMAP pixels (first pixel centre (0.5, 0.5)) of the
  *undistorted* images (pinhole part of each camera); ``E_ji`` the same for normalised coordinates.
- ``epipolar_band_95_px``: half-width of the band around the epipolar line in j (pinhole pixels of j) that
  holds the true correspondence of a floor point of image i with 95 % probability, pooled over the floor points
  the two cameras share and over the joint uncertainty of poses and calibration (``rigsfm.run.adjustment.uncertainty``);
  null when it cannot be estimated or the images share no view.
- ``world``: the frame of every pose (``rigsfm.run.world.frame``): by default the floor frame (z = 0 on the floor, z
  up, metres, origin under the rigs' centroid, x towards the first rig), with how the floor was found.
- per narrow image, ``ground``: one entry per plane z = h (the floor, then ``--plane-height``) with
  ``ground_from_image`` (undistorted COLMAP pixels -> plane metres, as ``F_ji``), the footprint polygon and
  the ground sampling distance at its centre; per pair, ``ground_overlap_m2`` (area both cameras see, per plane).
"""

from __future__ import annotations

import itertools
import logging
import shlex
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from rigsfm.core.conventions import CONVENTIONS, euler_zyx_degrees
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.geometry import align_points
from rigsfm.core.io import atomic_directory, write_json_atomic
from rigsfm.core.names import name_of
from rigsfm.core.serialise import camera_to_dict, pose_to_dict

if TYPE_CHECKING:
    from rigsfm.core.workspace import Workspace

logger = logging.getLogger(__name__)


def pinhole_matrix(camera: pycolmap.Camera) -> np.ndarray:
    return np.asarray(camera.calibration_matrix(), dtype=np.float64)


def fundamental_matrix(j_from_i: pycolmap.Rigid3d, camera_i: pycolmap.Camera, camera_j: pycolmap.Camera) -> np.ndarray:
    essential = np.asarray(pycolmap.essential_matrix_from_pose(j_from_i))
    f = np.linalg.inv(pinhole_matrix(camera_j)).T @ essential @ np.linalg.inv(pinhole_matrix(camera_i))
    return f / np.linalg.norm(f)


def narrow_images(reconstruction: pycolmap.Reconstruction) -> list[pycolmap.Image]:
    return sorted(
        (im for im in reconstruction.images.values() if im.has_pose and name_of(im).is_narrow),
        key=lambda im: im.name,
    )


def narrow_poses(reconstruction: pycolmap.Reconstruction, *, metric: bool, bands: dict | None = None,
                 world: dict | None = None, ground=None) -> dict:
    """The narrow-camera deliverable as a JSON-ready dict; ``bands``: ``(i, j) -> rigsfm.run.adjustment.bands.PairBand``;
    ``world`` (``WorldResult.to_dict()``) and ``ground`` (:class:`rigsfm.run.world.frame.GroundMaps`) when known."""
    images = narrow_images(reconstruction)
    bands = bands or {}
    entries = []
    for image in images:
        camera = reconstruction.cameras[image.camera_id]
        entries.append(
            {
                "name": image.name,
                "rig": name_of(image).rig,
                "camera": camera_to_dict(camera),
                "cam_from_world": pose_to_dict(image.cam_from_world()),
                "centre": image.projection_center().tolist(),
            }
        )
        if ground is not None:
            entries[-1]["ground"] = ground.per_image.get(image.name, [])
    pairs = []
    for image_i, image_j in itertools.combinations(images, 2):
        j_from_i = image_j.cam_from_world() * image_i.cam_from_world().inverse()
        camera_i = reconstruction.cameras[image_i.camera_id]
        camera_j = reconstruction.cameras[image_j.camera_id]
        centre_j_in_i = image_i.cam_from_world() * image_j.projection_center()
        distance = float(np.linalg.norm(centre_j_in_i))
        yaw, pitch, roll = euler_zyx_degrees(j_from_i.rotation.matrix())
        pairs.append(
            {
                "i": image_i.name,
                "j": image_j.name,
                "narrow_j_from_narrow_i": pose_to_dict(j_from_i),
                "euler_zyx_deg": {"yaw": yaw, "pitch": pitch, "roll": roll},
                "centre_direction_in_i": (centre_j_in_i / distance).tolist(),
                "distance_m" if metric else "distance_units": distance,
                "E_ji": np.asarray(pycolmap.essential_matrix_from_pose(j_from_i)).tolist(),
                "F_ji": fundamental_matrix(j_from_i, camera_i, camera_j).tolist(),
                **_band_entry(bands.get((image_i.name, image_j.name))),
            }
        )
        if ground is not None:
            pairs[-1]["ground_overlap_m2"] = ground.overlap(image_i.name, image_j.name)
    data: dict[str, object] = {"metric": metric, "units": "meters" if metric else "arbitrary",
                               "conventions": CONVENTIONS,
            "narrow": entries, "pairs": pairs}
    if world is not None:
        data["world"] = world
    if ground is not None:
        data["ground"] = {"plane_heights_m": list(ground.heights), "seen_by_two_or_more_m2": ground.seen_twice_m2}
    return data


def _band_entry(band) -> dict:
    if band is None:
        return {"epipolar_band_95_px": None, "epipolar_band_points": None, "epipolar_band_depth_range_m": None,
                "epipolar_band_p_below_85": None}
    return {"epipolar_band_95_px": band.band_px, "epipolar_band_points": band.points,
            "epipolar_band_depth_range_m": list(band.depth_range_m),
            "epipolar_band_p_below_85": band.predicted_below_85}


def write_model(reconstruction: pycolmap.Reconstruction, path: Path, *, overwrite: bool) -> Path:
    with atomic_directory(path, overwrite=overwrite) as tmp:
        reconstruction.write(tmp)
    return path


def write_points_ply(reconstruction: pycolmap.Reconstruction, path: Path, *, overwrite: bool) -> Path:
    if path.exists() and not overwrite:
        raise WorkspaceError(f"{path} already exists: pass --overwrite to replace it")
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        reconstruction.export_PLY(tmp)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_narrow_poses(reconstruction: pycolmap.Reconstruction, path: Path, *, metric: bool, overwrite: bool,
                       bands: dict | None = None, world: dict | None = None, ground=None) -> Path:
    return write_json_atomic(path, narrow_poses(reconstruction, metric=metric, bands=bands, world=world,
                                                ground=ground), overwrite=overwrite)


def _recorded_model(path: Path, *keys: str) -> str | None:
    """The model fingerprint a JSON file of OUT records under ``keys`` (None where it records none)."""
    import json

    try:
        value = json.loads(path.read_text(encoding="utf-8"))
        for key in keys:
            value = value.get(key)
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def earlier_outputs(workspace: Workspace) -> list[str]:
    """What in OUT was made from another model than ``OUT/sparse``: ``rigsfm track``'s series, ``rigsfm
    associate``'s default folder and each ``rigsfm export`` default folder, with the command that makes each again
    (an export from before exports recorded their model counts as another's: it was made before this model)."""
    from rigsfm.associate.output import MANIFEST as ASSOCIATE_MANIFEST
    from rigsfm.core.workspace import model_fingerprint
    from rigsfm.inspect.export import MANIFEST as EXPORT_MANIFEST

    if not workspace.sparse.is_dir():
        return []
    model = model_fingerprint(workspace.sparse)
    found = []
    if workspace.track.poses_json.is_file() and _recorded_model(workspace.track.poses_json, "reference",
                                                                  "fingerprint") != model:
        found.append(f"{workspace.track.root} (`rigsfm track {workspace.shell_root} NEW_IMAGES --overwrite`)")
    manifest = workspace.associate / ASSOCIATE_MANIFEST
    if manifest.is_file() and _recorded_model(manifest, "model") != model:
        found.append(f"{workspace.associate} (`rigsfm associate {workspace.shell_root} DETECTIONS --overwrite`)")
    if workspace.exports.is_dir():
        for folder in sorted(p for p in workspace.exports.iterdir() if (p / EXPORT_MANIFEST).is_file()):
            if _recorded_model(folder / EXPORT_MANIFEST, "model") != model:
                fmt = _recorded_model(folder / EXPORT_MANIFEST, "format") or folder.name
                dest = "" if folder.name == fmt else f" --dest {shlex.quote(str(folder))}"  # not its format's default
                found.append(f"{folder} (`rigsfm export {workspace.shell_root} --format {fmt}{dest} --overwrite`)")
    return found


def earlier_outputs_warning(workspace: Workspace) -> str | None:
    """One warning naming :func:`earlier_outputs`, or None."""
    found = earlier_outputs(workspace)
    if not found:
        return None
    return (f"MADE FROM THE EARLIER RESULT: {len(found)} output(s) in {workspace.root} were made from the result "
            f"this run replaced and no longer match it: {'; '.join(found)}; make each again with the command named "
            "(they are kept as they are)")


def changes_from(earlier: dict | None, now: dict) -> dict | None:
    """How the narrow cameras of ``now`` (a narrow_poses.json) differ from those of the result it replaces
    (``earlier``): per rig the largest rotation (deg) and centre shift (mm where both are metric, else None) of
    its narrow images in both, and the images in one only. Where both are in the floor frame they are compared as
    they are (it follows the rigs, so a moved rig shifts it a little too: ``compared`` 'floor'); else (the mapper's
    frame, arbitrary in each run, or a floor found in one only) the earlier cameras are first aligned onto the new
    ones by their centres (rigid, or with a scale where either is not metric: 'aligned'), and with fewer than three
    centres off one line they are not compared (no rigs, ``compared`` None)."""
    if not isinstance(earlier, dict) or not isinstance(earlier.get("narrow"), list):
        return None
    before = {str(e.get("name")): e for e in earlier["narrow"] if isinstance(e, dict)}
    after = {e["name"]: e for e in now["narrow"]}
    metric = earlier.get("metric") is True and now.get("metric") is True
    worlds = [(d.get("world") or {}).get("frame") for d in (earlier, now)]
    cameras = []
    for name in sorted(set(before) & set(after)):
        try:
            r0, r1 = (np.asarray(e["cam_from_world"]["rotation"], dtype=float) for e in (before[name], after[name]))
            c0, c1 = (np.asarray(e["centre"], dtype=float) for e in (before[name], after[name]))
        except (KeyError, TypeError, ValueError):
            continue
        if r0.shape == r1.shape == (3, 3) and c0.shape == c1.shape == (3,):
            cameras.append((name, r0, r1, c0, c1))
    compared: str | None = "floor"
    if worlds[0] != "floor" or worlds[1] != "floor":
        now_from_before = align_points(np.array([c[3] for c in cameras]), np.array([c[4] for c in cameras]),
                                       scaled=not metric)
        if now_from_before is None:
            compared, cameras = None, []
        else:
            compared, rotation = "aligned", now_from_before.rotation.matrix()
            cameras = [(name, r0 @ rotation.T, r1, now_from_before * c0, c1) for name, r0, r1, c0, c1 in cameras]
    rigs: dict[str, dict] = {}
    for name, r0, r1, c0, c1 in cameras:
        turn = r1 @ r0.T  # its angle from sine and cosine: arccos alone loses small angles to rounding
        sine = np.linalg.norm([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]]) / 2.0
        angle = float(np.degrees(np.arctan2(sine, (np.trace(turn) - 1.0) / 2.0)))
        rig = rigs.setdefault(after[name]["rig"], {"rotation_deg": 0.0, "centre_mm": 0.0 if metric else None})
        rig["rotation_deg"] = max(rig["rotation_deg"], angle)
        if metric:
            rig["centre_mm"] = max(rig["centre_mm"], 1000.0 * float(np.linalg.norm(c1 - c0)))
    return {"rigs": rigs, "new_images": sorted(set(after) - set(before)),
            "gone_images": sorted(set(before) - set(after)), "world_before": worlds[0], "world": worlds[1],
            "compared": compared}


def describe_changes(replaced: dict) -> str:
    """One line of :func:`changes_from` for the terminal."""
    rigs = replaced.get("rigs") or {}
    compared = replaced.get("compared", "floor")  # an earlier version's record: compared as they were
    worlds = f"{replaced.get('world_before') or 'unknown'}, this one's {replaced.get('world') or 'unknown'}"
    aligned = (f"once the earlier result's world ({replaced.get('world_before') or 'unknown'}) is aligned onto this "
               f"one's ({replaced.get('world') or 'unknown'})")
    where = {"floor": "each in its own floor frame", "aligned": aligned}.get(compared or "", "")
    parts = []
    if rigs and not replaced.get("new_images") and not replaced.get("gone_images") and all(
            v["rotation_deg"] < 1e-9 and (v.get("centre_mm") or 0.0) < 1e-6 for v in rigs.values()):
        return f"replaced the earlier result: the same narrow poses{', ' + where if compared == 'aligned' else ''} " \
               "(summary.json: replaced)"
    if rigs:
        rig, worst = max(rigs.items(), key=lambda item: item[1]["rotation_deg"])
        shifts = [(v["centre_mm"], name) for name, v in rigs.items() if v.get("centre_mm") is not None]
        text = f"narrow cameras turned by up to {worst['rotation_deg']:.3f} deg ({rig})"
        if shifts:
            shift, moved = max(shifts)
            text += f" and moved by up to {shift:.1f} mm ({moved})"
        parts.append(text)
    elif compared is None:
        parts.append(f"narrow poses not compared (the earlier result's world is {worlds}, and fewer than three "
                     "narrow cameras off one line are in both to align them)")
    for key, what in (("new_images", "new"), ("gone_images", "no longer in the result")):
        if replaced.get(key):
            parts.append(f"{len(replaced[key])} narrow image(s) {what} ({replaced[key][0]}"
                         f"{', ...' if len(replaced[key]) > 1 else ''})")
    return "replaced the earlier result: " + ("; ".join(parts) or "no narrow image in both") + \
        (f" ({where}; summary.json: replaced)" if where and rigs else " (summary.json: replaced)")
