"""E^sl (narrow_from_wide) from views both cameras saw: fixed intrinsics first, then a joint refinement.

Per common view only the corner ids seen by *both* cameras are used, so a narrow camera that sees part of
a ChArUco board still contributes. Views whose mono poses disagree with the others about the relative
pose are dropped (or, for a chessboard seen upside-down by one camera, re-ordered) before the fit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from rigsfm.calibrate.board import MIN_CORNERS, Detection
from rigsfm.calibrate.intrinsics import (
    CRITERIA,
    OUTLIER_FACTOR,
    OUTLIER_FLOOR_PX,
    CameraCalibration,
    correspondences,
)
from rigsfm.calibrate.joint import JointFit, joint_refine
from rigsfm.core.conventions import rotation_angle_deg
from rigsfm.core.errors import InputError, RigsfmError

logger = logging.getLogger(__name__)

MIN_STEREO_VIEWS = 3
CONSISTENCY_DEG = 5.0  # a view's relative rotation this far from the consensus is inconsistent
MAX_FOCAL_DRIFT = 0.02  # joint refinement may move a focal length by at most 2 % ...
MAX_PP_DRIFT = 0.02  # ... and a principal point by 2 % of the image width
RMS_TOLERANCE = 1.25  # ... and must fit each camera's own views within 25 % (+0.05 px) of its mono RMS
MAX_CONDITION = 1e14


@dataclass
class StereoFit:
    R: np.ndarray
    T: np.ndarray
    rms: float
    per_view: dict[str, tuple[float, float]]  # view -> (wide RMS, narrow RMS)
    K_wide: np.ndarray
    dist_wide: np.ndarray
    K_narrow: np.ndarray
    dist_narrow: np.ndarray

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.T))


@dataclass
class StereoCalibration:
    fixed: StereoFit  # intrinsics held at the mono values
    joint: StereoFit | None  # intrinsics + extrinsics refined together (over all views)
    use_joint: bool
    views: list[str]
    dropped: dict[str, str] = field(default_factory=dict)  # view -> reason
    notes: list[str] = field(default_factory=list)
    joint_detail: JointFit | None = None

    @property
    def final(self) -> StereoFit:
        return self.joint if self.use_joint and self.joint is not None else self.fixed


def _relative(rvec_w, tvec_w, rvec_n, tvec_n) -> tuple[np.ndarray, np.ndarray]:
    Rw, Rn = cv2.Rodrigues(rvec_w)[0], cv2.Rodrigues(rvec_n)[0]
    R = Rn @ Rw.T
    return R, tvec_n - R @ tvec_w


def _common(dw: Detection, dn: Detection, obj_points: np.ndarray):
    ids, iw, inn = np.intersect1d(dw.ids, dn.ids, return_indices=True)
    obj = obj_points[ids]
    if len(ids) < MIN_CORNERS or np.linalg.svd(obj[:, :2] - obj[:, :2].mean(0), compute_uv=False)[1] < 1e-6:
        return None
    return (obj.astype(np.float32).reshape(-1, 1, 3), dw.image_points[iw].astype(np.float32).reshape(-1, 1, 2),
            dn.image_points[inn].astype(np.float32).reshape(-1, 1, 2))


def _reversed(d: Detection, n_corners: int) -> Detection:
    return Detection(ids=(n_corners - 1 - d.ids)[::-1].copy(), image_points=d.image_points[::-1].copy())


def _stereo(data: dict, names: list[str], K1, d1, K2, d2, size, flags) -> StereoFit:
    obj = [data[n][0] for n in names]
    try:
        # OpenCV's stubs: None lets it estimate
        out = cv2.stereoCalibrateExtended(obj, [data[n][1] for n in names], [data[n][2] for n in names],  # type: ignore[call-overload]
                                          K1.copy(), d1.copy(), K2.copy(), d2.copy(), size, None, None,
                                          flags=flags, criteria=CRITERIA)
    except cv2.error as e:
        raise RigsfmError(f"OpenCV stereoCalibrate failed: {str(e).strip().splitlines()[-1]}") from e
    rms, K1o, d1o, K2o, d2o, R, T = out[:7]
    per_view = out[-1].reshape(-1, 2)
    return StereoFit(R=R, T=T.reshape(3), rms=float(rms),
                     per_view={n: (float(a), float(b)) for n, (a, b) in zip(names, per_view)},
                     K_wide=K1o, dist_wide=d1o.reshape(-1)[:5], K_narrow=K2o, dist_narrow=d2o.reshape(-1)[:5])


def _consensus(relatives: dict[str, np.ndarray]) -> np.ndarray:
    """The medoid relative rotation: the one closest (summed angle) to all others."""
    names = list(relatives)
    cost = [sum(rotation_angle_deg(relatives[a], relatives[b]) for b in names) for a in names]
    return relatives[names[int(np.argmin(cost))]]


def calibrate_stereo(wide: CameraCalibration, narrow: CameraCalibration, wide_det: dict[str, Detection | None],
                     narrow_det: dict[str, Detection | None], obj_points: np.ndarray, chessboard: bool,
                     where: str) -> StereoCalibration:
    dropped: dict[str, str] = {}
    notes: list[str] = []
    candidates = [n for n in wide.used_views if n in narrow.poses]
    data, relatives, corrected = {}, {}, {}
    for n in candidates:
        common = _common(wide_det[n], narrow_det[n], obj_points)  # type: ignore[arg-type]  # views detected in both
        if common is None:
            dropped[n] = f"fewer than {MIN_CORNERS} (non-collinear) corners seen by both cameras"
            continue
        data[n] = common
        relatives[n] = _relative(*wide.poses[n], *narrow.poses[n])[0]
    if len(data) >= MIN_STEREO_VIEWS:
        reference = _consensus(relatives)
        for n in list(data):
            angle = rotation_angle_deg(relatives[n], reference)
            if angle <= CONSISTENCY_DEG:
                continue
            if chessboard:  # one camera may have ordered the corners from the opposite end
                flipped = _reversed(narrow_det[n], len(obj_points))  # type: ignore[arg-type]  # views detected in both
                obj, img = obj_points[flipped.ids].astype(np.float32), flipped.image_points.astype(np.float32)
                ok, rvec, tvec = cv2.solvePnP(obj, img, narrow.K, narrow.dist)
                if ok and rotation_angle_deg(_relative(*wide.poses[n], rvec.reshape(3), tvec.reshape(3))[0],
                                             reference) <= CONSISTENCY_DEG:
                    # views detected in both
                    data[n] = _common(wide_det[n], flipped, obj_points)  # type: ignore[arg-type]
                    corrected[n] = flipped
                    notes.append(f"view {n}: narrow chessboard corners were ordered from the opposite end; reversed")
                    continue
            dropped[n] = f"relative pose {angle:.1f} deg away from the other views (bad detection?)"
            del data[n]
    names = sorted(data)
    if len(names) < MIN_STEREO_VIEWS:
        why = "; ".join(f"{n}: {r}" for n, r in sorted(dropped.items())[:5])
        raise InputError(
            f"{where}: only {len(names)} views usable for E^sl (need {MIN_STEREO_VIEWS}, better 8+): a view counts "
            f"when both cameras detected the board in it (same file name) with {MIN_CORNERS}+ common corners"
            + (f" ({why})" if why else "") + "; capture more views where the narrow camera sees the board too")
    size = wide.image_size
    while True:
        fixed = _stereo(data, names, wide.K, wide.dist, narrow.K, narrow.dist, size, cv2.CALIB_FIX_INTRINSIC)
        errors = {n: max(v) for n, v in fixed.per_view.items()}
        median = float(np.median(list(errors.values())))
        worst = max(errors, key=errors.get)  # type: ignore[arg-type]  # typeshed: get's overloads
        if (errors[worst] <= OUTLIER_FACTOR * median or errors[worst] <= OUTLIER_FLOOR_PX
                or len(names) <= MIN_STEREO_VIEWS):
            break
        dropped[worst] = f"stereo outlier: RMS {errors[worst]:.2f} px > {OUTLIER_FACTOR:g} x median {median:.2f} px"
        names.remove(worst)
    narrow_pairs = {n: narrow.pairs[n] for n in narrow.used_views if n not in dropped and n not in data}
    for n in names:  # orientation-consistent narrow correspondences of the E^sl views
        # views detected in both
        narrow_pairs[n] = correspondences(corrected.get(n, narrow_det[n]), obj_points)  # type: ignore[arg-type]
    result = StereoCalibration(fixed=fixed, joint=None, use_joint=False, views=names, dropped=dropped, notes=notes)
    try:
        detail = joint_refine(wide, narrow, narrow_pairs, fixed.R, fixed.T, names)
    except (cv2.error, ValueError, np.linalg.LinAlgError) as e:
        result.notes.append(f"joint refinement failed ({e}); kept the fixed-intrinsics E^sl")
        return result
    result.joint = StereoFit(R=detail.R, T=detail.T, rms=detail.rms_common, per_view=detail.per_view,
                             K_wide=detail.K_wide, dist_wide=detail.dist_wide, K_narrow=detail.K_narrow,
                             dist_narrow=detail.dist_narrow)
    result.joint_detail = detail
    problem = _joint_problem(detail, fixed, wide, narrow)
    if problem:
        result.notes.append(f"joint refinement rejected: {problem}; kept the fixed-intrinsics E^sl and mono intrinsics")
    else:
        result.use_joint = True
        result.notes.append(f"joint refinement accepted (all {len(wide.used_views)} wide + {len(narrow_pairs)} narrow "
                            f"views): E^sl-view RMS {fixed.rms:.3f} -> {detail.rms_common:.3f} px, per-camera RMS "
                            f"{wide.rms:.3f} -> {detail.rms_wide:.3f} (wide), {narrow.rms:.3f} -> {detail.rms_narrow:.3f} px (narrow)")
    logger.info("%s: E^sl from %d views, baseline %.4f m, RMS %.3f px (%s)", where, len(names),
                result.final.baseline, result.final.rms, "joint" if result.use_joint else "fixed intrinsics")
    return result


def _joint_problem(joint: JointFit, fixed: StereoFit, wide: CameraCalibration, narrow: CameraCalibration) -> str:
    values = [joint.rms_wide, joint.rms_common, *np.ravel(joint.T), *np.ravel(joint.K_narrow), *joint.std]
    if not np.all(np.isfinite(values)) or joint.condition > MAX_CONDITION:
        return f"ill-conditioned (normal matrix condition {joint.condition:.2g})"
    for cam, K, rms in ((wide, joint.K_wide, joint.rms_wide), (narrow, joint.K_narrow, joint.rms_narrow)):
        drift = np.abs(np.diag(K)[:2] / np.diag(cam.K)[:2] - 1.0).max()
        if drift > MAX_FOCAL_DRIFT:
            return f"ill-conditioned: {cam.sensor} focal length moved {100 * drift:.1f} % (> {100 * MAX_FOCAL_DRIFT:g} %)"
        shift = np.abs(K[:2, 2] - cam.K[:2, 2]).max() / cam.image_size[0]
        if shift > MAX_PP_DRIFT:
            return f"ill-conditioned: {cam.sensor} principal point moved {100 * shift:.1f} % of the image width"
        if np.isfinite(rms) and rms > RMS_TOLERANCE * cam.rms + 0.05:
            return (f"with the rig constraint the {cam.sensor} views fit worse (RMS {cam.rms:.3f} -> {rms:.3f} px): "
                    "the rig may not be rigid or the frames not synchronised")
    return ""
