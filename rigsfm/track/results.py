"""OUT/track/poses.json and poses.csv: per rig and frame, the pose change from the reference.

Conventions (also in the file's ``conventions`` block): a change is ``cam_ref_from_cam``, the motion of
a camera expressed in its own baseline frame (x_ref = R x_new + t). ``rotation_change_deg`` is its angle,
``translation_change_mm`` the distance its centre moved (``|t|``). The narrow camera's change follows
from the wide camera's through the fixed E^sl: same angle, centre shift differing by the baseline lever.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.conventions import rotation_vector
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.serialise import pose_to_dict
from rigsfm.track.options import Thresholds
from rigsfm.track.reference import ReferenceMap, ReferenceRig
from rigsfm.track.verdict import classify

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
CONVENTIONS = {
    "change": "cam_ref_from_cam: x_ref = R @ x_new + t, the camera's motion in its baseline frame",
    "rotation_change_deg": "angle of R",
    "translation_change_mm": "|t|: distance the camera centre moved",
    "rotation_vector_deg": "axis * angle of R (wide camera; the narrow camera's is E^sl-rotated)",
    "translation_mm": "t of the wide camera's change, in its baseline frame",
    "baseline": "the reference wide image registered from its own observations in OUT/sparse",
    "order": "frames sorted by file name within each rig",
}
CSV_COLUMNS = ("rig", "frame", "status", "flagged", "narrow_rotation_change_deg", "narrow_translation_change_mm",
               "wide_rotation_change_deg", "wide_translation_change_mm", "inliers", "reprojection_error_px",
               "sensors", "reason")


def _change(cam_ref_from_world: pycolmap.Rigid3d, cam_from_world: pycolmap.Rigid3d) -> dict:
    change = cam_ref_from_world * cam_from_world.inverse()
    return {"rotation_change_deg": float(np.degrees(change.rotation.angle())),
            "translation_change_mm": float(1000.0 * np.linalg.norm(change.translation)),
            "rotation_vector_deg": np.degrees(rotation_vector(change.rotation)).tolist(),
            "translation_mm": (1000.0 * np.asarray(change.translation)).tolist()}


def derive(record: dict, rig: ReferenceRig) -> dict:
    """A worker's record plus the wide and narrow poses and their changes from the baseline."""
    entry = dict(record)
    if record["status"] != "registered":
        return entry
    wide_from_world = pycolmap.Rigid3d(np.asarray(record["wide_from_world"], dtype=np.float64))
    baseline = rig.baseline_wide_from_world
    entry["wide_from_world"] = pose_to_dict(wide_from_world)
    entry["wide"] = _change(baseline, wide_from_world)
    if rig.narrow_from_wide is not None:
        narrow_from_wide = rig.narrow_from_wide
        entry["narrow_from_world"] = pose_to_dict(narrow_from_wide * wide_from_world)
        entry["narrow"] = _change(narrow_from_wide * baseline, narrow_from_wide * wide_from_world)
    return entry


def change_vector(entry: dict) -> np.ndarray:
    """[w (rad), d (m)] in the convention of :mod:`rigsfm.track.verdict` (w = -rotation vector of the change)."""
    return np.concatenate([-np.radians(entry["wide"]["rotation_vector_deg"]),
                           np.asarray(entry["wide"]["translation_mm"]) / 1000.0])


def load_poses(path: Path, reference: ReferenceMap) -> dict:
    """Existing results (empty if none); refuses results made against another reference model."""
    if not path.is_file():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise WorkspaceError(f"'{path}' is not valid JSON ({e}); pass --overwrite to start the series anew") from e
    if data.get("reference", {}).get("fingerprint") != reference.fingerprint:
        raise WorkspaceError(f"'{path}' was tracked against another reference model than '{reference.sparse}'; "
                             "pass --overwrite to start the series anew against this one")
    return {(f["rig"], f["frame"]): f for rig in data.get("rigs", {}).values() for f in rig.get("frames", [])}


def assemble(frames: dict[tuple[str, str], dict], reference: ReferenceMap, thresholds: Thresholds) -> dict:
    """poses.json content: per rig its baseline, frames in order, flags and verdict."""
    rigs = {}
    for name, rig in sorted(reference.rigs.items()):
        entries = sorted((f for (r, _), f in frames.items() if r == name), key=lambda f: f["frame"])
        if not entries:
            continue
        registered = [f for f in entries if f["status"] == "registered"]
        verdict = classify([f["frame"] for f in registered], [change_vector(f) for f in registered],
                           [f["covariance"] for f in registered], rig.baseline_covariance, thresholds)
        for f in entries:
            f["flagged"] = False
        for f, flag in zip(registered, verdict.flagged):
            f["flagged"] = bool(flag)
        rigs[name] = {
            "reference_image": rig.reference_image,
            "baseline_wide_from_world": pose_to_dict(rig.baseline_wide_from_world),
            "reference_wide_from_world": pose_to_dict(rig.wide_from_world),
            "verdict": verdict.to_dict(),
            "frames": entries,
        }
    return {"version": FORMAT_VERSION,
            "reference": {"sparse": reference.sparse, "fingerprint": reference.fingerprint},
            "thresholds": {"rotation_deg": thresholds.rotation_deg, "translation_mm": thresholds.translation_mm,
                           "significance_chi2": thresholds.significance_chi2,
                           "min_persist_frames": thresholds.min_persist_frames},
            "conventions": CONVENTIONS, "rigs": rigs}


def to_csv(poses: dict) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for name, rig in poses["rigs"].items():
        for f in rig["frames"]:
            narrow, wide = f.get("narrow", {}), f.get("wide", {})

            def number(d: dict, key: str, digits: int = 5) -> str:
                return "" if d.get(key) is None else f"{d[key]:.{digits}f}"

            writer.writerow([name, f["frame"], f["status"], int(f.get("flagged", False)),
                             number(narrow, "rotation_change_deg"), number(narrow, "translation_change_mm", 3),
                             number(wide, "rotation_change_deg"), number(wide, "translation_change_mm", 3),
                             f.get("num_inliers", ""), number(f, "reprojection_error_px", 4),
                             "+".join(f.get("used_sensors", [])), f.get("reason") or ""])
    return out.getvalue()
