"""Single-camera calibration from board detections, with outlier-view rejection and coverage check.

The distortion model follows what is estimated: k1, k2, p1, p2 -> COLMAP ``OPENCV``; with k3 as well ->
``FULL_OPENCV`` (k4..k6 = 0). ``Distortion.AUTO`` adds k3 only if it lowers the RMS by >= 5 %.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
import pycolmap

from rigsfm.calibrate.board import MIN_CORNERS, Detection
from rigsfm.calibrate.options import Distortion
from rigsfm.core.conventions import colmap_from_opencv_pixels
from rigsfm.core.errors import InputError, RigsfmError

logger = logging.getLogger(__name__)

MIN_VIEWS = 3
GOOD_VIEWS = 8  # fewer poses calibrate, but with a focal and distortion poorly determined (docs/inputs.md)
OUTLIER_FACTOR = 3.0  # a view is an outlier if its RMS > 3 x the median view RMS ...
OUTLIER_FLOOR_PX = 0.5  # ... and above this (tiny RMS differences are noise, not outliers)
MAX_VIEW_RMS_PX = 5.0  # any view above this is rejected whatever the median
K3_GAIN = 0.05  # auto distortion: use k3 only if the RMS drops by at least 5 %
COVERAGE_GRID = (8, 6)
MIN_COVERAGE = 0.30
CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)


@dataclass
class ViewResult:
    name: str
    corners: int
    rms: float | None  # px, under the final intrinsics (None if never fitted)
    used: bool
    reason: str = ""


@dataclass
class CameraCalibration:
    """Intrinsics of one camera in OpenCV conventions, plus the evidence behind them."""

    sensor: str
    image_size: tuple[int, int]  # (width, height)
    K: np.ndarray
    dist: np.ndarray  # (k1, k2, p1, p2, k3)
    model: str  # OPENCV or FULL_OPENCV
    rms: float
    views: list[ViewResult]
    poses: dict[str, tuple[np.ndarray, np.ndarray]]  # view -> (rvec, tvec), cam_from_board
    coverage: float
    std_intrinsics: np.ndarray  # std dev of fx, fy, cx, cy, k1, k2, p1, p2, k3
    pairs: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # view -> (object, image) points
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def used_views(self) -> list[str]:
        return [v.name for v in self.views if v.used]

    def colmap_camera(self) -> pycolmap.Camera:
        return colmap_camera(self.K, self.dist, self.image_size, self.model)


def colmap_camera(K: np.ndarray, dist: np.ndarray, image_size: tuple[int, int], model: str) -> pycolmap.Camera:
    """A pycolmap camera from OpenCV K and distortion; the principal point moves to COLMAP's convention."""
    cx, cy = colmap_from_opencv_pixels(np.array([K[0, 2], K[1, 2]]))
    d = np.zeros(5)
    d[: min(5, len(np.ravel(dist)))] = np.ravel(dist)[:5]
    params = [K[0, 0], K[1, 1], cx, cy, d[0], d[1], d[2], d[3]]
    if model == "FULL_OPENCV":
        params += [d[4], 0.0, 0.0, 0.0]
    elif abs(d[4]) > 0:
        raise RigsfmError(f"internal: k3 = {d[4]} cannot be stored in the OPENCV model")
    return pycolmap.Camera(model=model, width=int(image_size[0]), height=int(image_size[1]), params=params)


def correspondences(detection: Detection, object_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (object_points[detection.ids].astype(np.float32).reshape(-1, 1, 3),
            detection.image_points.astype(np.float32).reshape(-1, 1, 2))


def view_rms(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray) -> float:
    """RMS reprojection error of one view under fixed intrinsics (pose re-estimated)."""
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        return float("inf")
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    return float(np.sqrt(np.mean(np.sum((proj - img).reshape(-1, 2) ** 2, axis=1))))


def _fit(obj, img, size, k3: bool):
    flags = 0 if k3 else cv2.CALIB_FIX_K3
    try:
        rms, K, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(
            obj, img, size, None, None, flags=flags, criteria=CRITERIA)  # type: ignore[call-overload]  # None: no guess
    except cv2.error as e:
        raise RigsfmError(f"OpenCV calibrateCamera failed: {str(e).strip().splitlines()[-1]}") from e
    return float(rms), K, dist.reshape(-1)[:5], rvecs, tvecs, std_in.reshape(-1)[:9], per_view.reshape(-1)


def coverage_fraction(points: list[np.ndarray], image_size: tuple[int, int]) -> float:
    """Fraction of the cells of an 8x6 grid over the image that contain at least one detected corner."""
    cols, rows = COVERAGE_GRID
    hit = np.zeros((rows, cols), bool)
    w, h = image_size
    for p in points:
        p = p.reshape(-1, 2)
        c = np.clip((p[:, 0] / w * cols).astype(int), 0, cols - 1)
        r = np.clip((p[:, 1] / h * rows).astype(int), 0, rows - 1)
        hit[r, c] = True
    return float(hit.mean())


def calibrate_camera(sensor: str, detections: dict[str, Detection | None], object_points: np.ndarray,
                     image_size: tuple[int, int], distortion: Distortion = Distortion.AUTO,
                     where: str = "") -> CameraCalibration:
    """Calibrate one camera from its detections (view name -> Detection or None)."""
    try:
        distortion = Distortion(distortion)
    except ValueError:
        raise InputError(f"distortion must be one of {', '.join(Distortion)}, got {distortion!r}") from None
    where = where or sensor
    views = {n: ViewResult(n, 0 if d is None else len(d), None, False,
                           "board not found" if d is None else "") for n, d in detections.items()}
    active = [n for n, d in detections.items() if d is not None and len(d) >= MIN_CORNERS]
    for n, d in detections.items():
        if d is not None and len(d) < MIN_CORNERS:
            views[n].reason = f"only {len(d)} corners (need {MIN_CORNERS})"
    if len(active) < MIN_VIEWS:
        raise InputError(f"{where}: the board was detected in only {len(active)} image{'' if len(active) == 1 else 's'} (need at least "
                         f"{MIN_VIEWS}, better {GOOD_VIEWS} or more); capture more views with the whole board or more of it visible")
    # active: detected
    pairs = {n: correspondences(detections[n], object_points) for n in active}  # type: ignore[arg-type]
    k3 = distortion == Distortion.FULL_OPENCV
    while True:
        fit = _fit([pairs[n][0] for n in active], [pairs[n][1] for n in active], image_size, k3)
        per_view = fit[6]
        median = float(np.median(per_view))
        worst = int(np.argmax(per_view))
        too_far = per_view[worst] > OUTLIER_FACTOR * median and per_view[worst] > OUTLIER_FLOOR_PX
        if not (too_far or per_view[worst] > MAX_VIEW_RMS_PX) or len(active) <= MIN_VIEWS:
            break
        name = active.pop(worst)
        views[name].rms = float(per_view[worst])
        views[name].reason = (f"outlier: view RMS {per_view[worst]:.2f} px > {OUTLIER_FACTOR:g} x median "
                              f"{median:.2f} px" if too_far else
                              f"outlier: view RMS {per_view[worst]:.2f} px > {MAX_VIEW_RMS_PX:g} px")
        logger.info("%s: rejected view %s (%s)", where, name, views[name].reason)
    notes = []
    if distortion == Distortion.AUTO:
        with_k3 = _fit([pairs[n][0] for n in active], [pairs[n][1] for n in active], image_size, True)
        gain = 1.0 - with_k3[0] / fit[0]
        if gain >= K3_GAIN:
            fit = with_k3
            notes.append(f"k3 estimated: it lowers the RMS by {100 * gain:.1f} % (>= {100 * K3_GAIN:g} %)")
        else:
            notes.append(f"k3 fixed at 0: estimating it lowers the RMS by only {100 * gain:.1f} %")
        k3 = gain >= K3_GAIN
    rms, K, dist, rvecs, tvecs, std_in, per_view = fit
    poses = {}
    for i, n in enumerate(active):
        views[n].used, views[n].rms, views[n].reason = True, float(per_view[i]), ""
        poses[n] = (rvecs[i].reshape(3), tvecs[i].reshape(3))
    for n, v in views.items():  # rejected views: their error under the final intrinsics
        if not v.used and n in pairs and v.reason.startswith("outlier"):
            v.rms = view_rms(*pairs[n], K, dist)
    cov = coverage_fraction([pairs[n][1] for n in active], image_size)
    result = CameraCalibration(sensor=sensor, image_size=image_size, K=K, dist=dist,
                               model="FULL_OPENCV" if k3 else "OPENCV", rms=rms, views=list(views.values()),
                               poses=poses, coverage=cov, std_intrinsics=std_in,
                               pairs={n: pairs[n] for n in active}, notes=notes)
    if cov < MIN_COVERAGE:
        result.warnings.append(f"{where}: detected corners cover only {100 * cov:.0f} % of the image "
                               f"({COVERAGE_GRID[0]}x{COVERAGE_GRID[1]} grid cells); distortion is poorly "
                               "constrained near the edges: add views with the board near the image borders")
    if len(active) < GOOD_VIEWS:
        result.warnings.append(f"{where}: only {len(active)} board poses used, {GOOD_VIEWS} or more are needed for "
                               "well-determined intrinsics; photograph the board in more poses (tilted up to ~45°, "
                               "together covering the whole image)")
    rejected = [v for v in result.views if not v.used and v.reason.startswith("outlier")]
    if len(rejected) > len(active) / 2:
        result.warnings.append(f"{where}: {len(rejected)} views rejected as outliers; check the detections")
    logger.info("%s: %d views, RMS %.3f px, f = %.2f/%.2f px, model %s, coverage %.0f %%", where, len(active),
                rms, K[0, 0], K[1, 1], result.model, 100 * cov)
    return result
