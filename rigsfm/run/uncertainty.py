"""Uncertainty of the narrow poses, and the 95 % epipolar band it implies.

1. ``rig_pose_covariance``: the joint covariance of every rig pose (``rig_from_world`` = the wide
   camera's pose) from COLMAP's bundle-adjustment covariance (``pycolmap.estimate_ba_covariance``), on
   the same problem as ``constrained_bundle_adjustment``: points and rig poses free, intrinsics and E^sl
   constant, and the same gauge (one frame fixed; plus COLMAP's TWO_CAMS_FROM_WORLD scale gauge when the
   scale is not observed by narrow observations). The squared loss is used (the covariance of the robust
   solution's inliers) and the covariance is scaled by the estimated pixel variance of the residuals.
   Tangent convention (converted from Ceres' quaternion manifold, whose delta is half the rotation
   vector): ``R' = Exp(omega) R``, ``t' = t + dt``, vector ``[omega, dt]`` per frame.
2. Narrow poses follow exactly as ``narrow_from_world = narrow_from_wide * rig_from_world`` with E^sl
   constant, so samples of the rig poses give samples of every narrow pose and relative pose.
3. ``epipolar_band``: for points on a grid of narrow image i at every depth at which they would appear
   inside narrow image j (depths sampled from 0.1x to 100x the centre distance, kept where the estimated
   projection falls in image j: the whole part of each epipolar line that crosses image j), the
   perpendicular distance (pinhole pixels of camera j, the frame of ``F_ji``) between the point's
   projection under a sampled relative pose and the estimated epipolar line. The band half-width is the
   largest, over grid points and depths, of the 95 % quantile over samples: the true correspondence of
   any point seen by both cameras lies within +- that many pixels of its epipolar line with >= 95 %
   probability. No depth prior is assumed beyond "visible in image j".
   Not included: errors of rigs.yaml itself (E^sl, intrinsics) unless ``calibration_sigma`` is given.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from rigsfm.core.geometry import project
from rigsfm.core.residuals import reprojection_errors
from rigsfm.run.adjust import fixed_calibration_problem, has_narrow_observations

logger = logging.getLogger(__name__)

BAND_PROBABILITY = 0.95


@dataclass(frozen=True)
class RigPoseCovariance:
    frame_ids: tuple[int, ...]  # block order of ``covariance``
    covariance: np.ndarray  # (6F, 6F), per frame [omega (rad), dt (m)]; R' = Exp(omega) R, t' = t + dt
    sigma_px: float  # estimated reprojection noise (per coordinate) that scales the covariance
    fixed_frame_id: int

    def block(self, frame_id: int) -> np.ndarray:
        k = self.frame_ids.index(frame_id)
        return self.covariance[6 * k:6 * k + 6, 6 * k:6 * k + 6]


@dataclass(frozen=True)
class CalibrationSigma:
    """Optional standard errors of rigs.yaml's E^sl, per axis (independent per rig)."""

    rotation_deg: float = 0.0
    translation_m: float = 0.0


def _ref_image_id(reconstruction: pycolmap.Reconstruction, frame: pycolmap.Frame) -> int:
    return next(d.id for d in frame.image_ids if reconstruction.image(d.id).is_ref_in_frame())


def _residual_sigma(reconstruction: pycolmap.Reconstruction, num_pose_params: int) -> float:
    errors = np.concatenate([e for e in reprojection_errors(reconstruction).values()] or [np.zeros(0)])
    dof = 2 * errors.size - 3 * reconstruction.num_points3D() - num_pose_params
    return float(np.sqrt(np.sum(errors**2) / dof)) if dof > 0 else float("nan")


def rig_pose_covariance(reconstruction: pycolmap.Reconstruction) -> RigPoseCovariance | None:
    """Joint covariance of all registered rig poses, or None when COLMAP cannot estimate it."""
    rec = pycolmap.Reconstruction(reconstruction)
    frame_ids = tuple(sorted(rec.reg_frame_ids()))
    if len(frame_ids) < 2:
        return None
    # A frame whose reference image observes no point has no parameter block in the problem, and COLMAP's
    # covariance then aborts the whole process ("Parameter block not found"): refuse before calling it.
    weak = [f for f in frame_ids if rec.image(_ref_image_id(rec, rec.frame(f))).num_points3D < 6]
    if weak:
        logger.warning("No pose covariance: frame(s) %s observe fewer than 6 points", weak)
        return None
    ba, config = fixed_calibration_problem(rec)
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    image_ids = sorted(rec.reg_image_ids())
    fixed_frame = rec.image(image_ids[0]).frame_id
    config.set_constant_rig_from_world_pose(fixed_frame)
    subset_frame, subset_dim = None, None
    if not has_narrow_observations(rec):
        # Scale unobserved: COLMAP's TWO_CAMS_FROM_WORLD gauge also fixes, in the first other frame (by
        # image id), the translation coordinate of largest baseline to the fixed frame (as in the BA).
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        fixed_pose = rec.frame(fixed_frame).rig_from_world
        for image_id in image_ids:
            frame_id = rec.image(image_id).frame_id
            if frame_id == fixed_frame:
                continue
            baseline = (fixed_pose * rec.frame(frame_id).rig_from_world.inverse()).translation
            if np.abs(baseline).max() > 1e-9:
                subset_frame, subset_dim = frame_id, int(np.argmax(np.abs(baseline)))
                break
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba, config, rec)
    options = pycolmap.BACovarianceOptions(params=pycolmap.BACovarianceOptionsParams.POSES)
    free = [f for f in frame_ids if f != fixed_frame]
    poses = []
    for frame_id in free:
        param = pycolmap.ExperimentalPoseParam()
        param.image_id = _ref_image_id(rec, rec.frame(frame_id))
        param.cam_from_world = rec.frame(frame_id).rig_from_world.params[:4]  # a view: the block's address
        poses.append(param)
    options.experimental_custom_poses = poses
    try:
        covariance = pycolmap.estimate_ba_covariance(options, rec, adjuster)
    except Exception as error:  # COLMAP throws on a rank-deficient problem
        logger.warning("Bundle-adjustment covariance failed: %s", error)
        return None
    if covariance is None:
        logger.warning("Bundle-adjustment covariance could not be estimated")
        return None

    def dims(frame_id: int) -> list[int]:  # which of the 6 tangent dimensions are free
        return [d for d in range(6) if not (frame_id == subset_frame and d == 3 + subset_dim)]

    full = np.zeros((6 * len(frame_ids), 6 * len(frame_ids)))
    for a in free:
        for b in free:
            id_a, id_b = (_ref_image_id(rec, rec.frame(f)) for f in (a, b))
            block = covariance.get_cam_cov_from_world(id_a) if a == b else \
                covariance.get_cam_cross_cov_from_world(id_a, id_b)
            if block is None:
                return None
            rows = [6 * frame_ids.index(a) + d for d in dims(a)]
            cols = [6 * frame_ids.index(b) + d for d in dims(b)]
            full[np.ix_(rows, cols)] = block
    # Ceres' EigenQuaternionManifold: q' = [cos|d|, sin|d| d/|d|] * q, a rotation by 2|d|: omega = 2 d.
    scale = np.tile(np.array([2.0, 2.0, 2.0, 1.0, 1.0, 1.0]), len(frame_ids))
    full *= np.outer(scale, scale)
    sigma = _residual_sigma(rec, sum(len(dims(f)) for f in free))
    if not np.isfinite(sigma) or not np.all(np.isfinite(full)):  # a rank-deficient (undetermined) network
        logger.warning("No pose covariance: the bundle adjustment problem is not fully determined")
        return None
    return RigPoseCovariance(frame_ids, full * sigma**2, sigma, fixed_frame)


def sample_narrow_from_world(reconstruction: pycolmap.Reconstruction, covariance: RigPoseCovariance,
                             image_names: list[str], num_samples: int, rng: np.random.Generator,
                             calibration_sigma: CalibrationSigma | None = None) -> dict[str, tuple]:
    """Samples (R: (S,3,3), t: (S,3)) of ``narrow_from_world`` for each named narrow image."""
    values, vectors = np.linalg.eigh(covariance.covariance)
    root = vectors * np.sqrt(np.clip(values, 0.0, None))
    delta = rng.standard_normal((num_samples, root.shape[0])) @ root.T
    rig_samples = {}
    for k, frame_id in enumerate(covariance.frame_ids):
        pose = reconstruction.frame(frame_id).rig_from_world
        d = delta[:, 6 * k:6 * k + 6]
        rotations = Rotation.from_rotvec(d[:, :3]).as_matrix() @ pose.rotation.matrix()
        rig_samples[frame_id] = (rotations, np.asarray(pose.translation) + d[:, 3:])
    out = {}
    for name in image_names:
        image = reconstruction.find_image_with_name(name)
        frame = reconstruction.frame(image.frame_id)
        narrow_from_rig = reconstruction.rig(frame.rig_id).sensor_from_rig(
            reconstruction.cameras[image.camera_id].sensor_id)
        r_e = np.broadcast_to(narrow_from_rig.rotation.matrix(), (num_samples, 3, 3))
        t_e = np.broadcast_to(np.asarray(narrow_from_rig.translation), (num_samples, 3))
        if calibration_sigma is not None and (calibration_sigma.rotation_deg or calibration_sigma.translation_m):
            noise = rng.standard_normal((num_samples, 3)) * np.radians(calibration_sigma.rotation_deg)
            r_e = Rotation.from_rotvec(noise).as_matrix() @ r_e
            t_e = t_e + rng.standard_normal((num_samples, 3)) * calibration_sigma.translation_m
        r_rig, t_rig = rig_samples[image.frame_id]
        out[name] = (r_e @ r_rig, np.einsum("sij,sj->si", r_e, t_rig) + t_e)
    return out


def grid_pixels(camera: pycolmap.Camera, n: int = 5, margin: float = 0.1) -> np.ndarray:
    """An n x n grid of pixels (COLMAP convention) inside the image, ``margin`` from its borders."""
    u = np.linspace(margin, 1.0 - margin, n) * camera.width
    v = np.linspace(margin, 1.0 - margin, n) * camera.height
    return np.array([(x, y) for y in v for x in u], dtype=np.float64)


def line_distances(camera_j: pycolmap.Camera, lines: np.ndarray, points_in_j: np.ndarray) -> np.ndarray:
    """Signed distance (pinhole pixels of j) of the projection of camera-j points from pixel lines."""
    k_j = np.asarray(camera_j.calibration_matrix())
    projected = points_in_j @ k_j.T
    projected = projected / projected[..., 2:3]
    return np.sum(lines * projected, axis=-1) / np.linalg.norm(lines[..., :2], axis=-1)


def epipolar_lines(camera_i: pycolmap.Camera, camera_j: pycolmap.Camera, j_from_i: pycolmap.Rigid3d,
                   pixels_i: np.ndarray) -> np.ndarray:
    """Lines (a, b, c) in camera j's pinhole pixels for raw pixels of image i (distortion removed)."""
    rays = np.asarray(camera_i.cam_from_img(np.asarray(pixels_i, dtype=np.float64)))
    rays = np.column_stack([rays, np.ones(len(rays))])
    essential = np.asarray(pycolmap.essential_matrix_from_pose(j_from_i))
    k_j = np.asarray(camera_j.calibration_matrix())
    return (np.linalg.inv(k_j).T @ essential @ rays.T).T


def band_quantiles(samples: dict[str, tuple], name_i: str, name_j: str, camera_j: pycolmap.Camera,
                   points_i: np.ndarray, lines: np.ndarray, probability: float = BAND_PROBABILITY) -> np.ndarray:
    """Per point of camera i (metres, camera-i frame): the ``probability`` quantile over pose samples of
    its projection's distance from its estimated epipolar line ``lines`` (pinhole pixels of j)."""
    r_i, t_i = samples[name_i]
    r_j, t_j = samples[name_j]
    r_ji = r_j @ np.transpose(r_i, (0, 2, 1))
    t_ji = t_j - np.einsum("sij,sj->si", r_ji, t_i)
    sampled = np.einsum("sij,pj->spi", r_ji, points_i) + t_ji[:, None, :]
    distances = np.where(sampled[..., 2] > 0, np.abs(line_distances(camera_j, lines[None], sampled)), np.inf)
    return np.quantile(distances, probability, axis=0)


def epipolar_band(reconstruction: pycolmap.Reconstruction, samples: dict[str, tuple], name_i: str, name_j: str,
                  grid: int = 7, num_depths: int = 48,
                  probability: float = BAND_PROBABILITY) -> tuple[float, tuple[float, float]]:
    """Half-width (px) of the band around epipolar lines in j holding the true correspondence, and the
    range of depths (m, in camera i) at which the grid points appear in image j."""
    image_i, image_j = (reconstruction.find_image_with_name(n) for n in (name_i, name_j))
    camera_i, camera_j = reconstruction.cameras[image_i.camera_id], reconstruction.cameras[image_j.camera_id]
    j_from_i = image_j.cam_from_world() * image_i.cam_from_world().inverse()
    pixels = grid_pixels(camera_i, grid)
    rays = np.column_stack([np.asarray(camera_i.cam_from_img(pixels)), np.ones(len(pixels))])
    distance = float(np.linalg.norm(j_from_i.translation))
    depths = np.geomspace(0.1 * distance, 100.0 * distance, num_depths)
    points_i = (rays[:, None, :] * depths[None, :, None]).reshape(-1, 3)  # (P*D, 3), camera i
    lines = np.repeat(epipolar_lines(camera_i, camera_j, j_from_i, pixels), num_depths, axis=0)
    in_j = np.asarray(j_from_i * points_i)
    keep = in_j[:, 2] > 0
    projected = in_j[keep] @ np.asarray(camera_j.calibration_matrix()).T
    projected = projected[:, :2] / projected[:, 2:]
    inside = ((projected >= 0) & (projected <= [camera_j.width, camera_j.height])).all(axis=1)
    keep[np.flatnonzero(keep)[~inside]] = False
    if not keep.any():
        return float("nan"), (float("nan"), float("nan"))
    seen_depths = np.tile(depths, len(pixels))[keep]
    quantiles = band_quantiles(samples, name_i, name_j, camera_j, points_i[keep], lines[keep], probability)
    band = float(quantiles.max())
    return band, (float(seen_depths.min()), float(seen_depths.max()))


def narrow_epipolar_bands(reconstruction: pycolmap.Reconstruction, pairs: list[tuple[str, str]],
                          num_samples: int = 400, seed: int = 0,
                          calibration_sigma: CalibrationSigma | None = None) -> dict[tuple[str, str], dict]:
    """Per narrow pair: ``{"band_px", "depth_range_m", "sigma_px"}``; pairs whose images share no view are
    left out; empty when the covariance is unavailable."""
    covariance = rig_pose_covariance(reconstruction)
    if covariance is None:
        return {}
    rng = np.random.default_rng(seed)
    names = sorted({n for pair in pairs for n in pair})
    samples = sample_narrow_from_world(reconstruction, covariance, names, num_samples, rng, calibration_sigma)
    bands = {}
    for name_i, name_j in pairs:
        band, depth_range = epipolar_band(reconstruction, samples, name_i, name_j)
        if np.isfinite(band):
            bands[(name_i, name_j)] = {"band_px": band, "depth_range_m": list(depth_range),
                                       "sigma_px": covariance.sigma_px}
    return bands


def correspondence_check(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction, name_i: str,
                         name_j: str, world_points: np.ndarray,
                         samples: dict[str, tuple] | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Validation against ground truth: distances (px) of true correspondences from estimated lines, and
    (given pose ``samples``) each one's predicted 95 % half-width at its own pixel and true depth.

    ``world_points`` (truth's frame) are projected with the true poses and cameras into both raw images;
    those seen by both give a true pixel pair, whose image-i pixel defines the estimated epipolar line in
    j (estimated cameras and pose) and whose image-j pixel (undistorted with the estimated camera j) is
    measured against it.
    """
    pixels, depths = [], None
    for name in (name_i, name_j):
        image = truth.find_image_with_name(name)
        camera = truth.cameras[image.camera_id]
        in_cam = np.asarray(image.cam_from_world() * np.asarray(world_points, dtype=np.float64))
        pixels.append(project(camera, in_cam))
        depths = in_cam[:, 2] if depths is None else depths
    both = pixels[0][1] & pixels[1][1]
    if not both.any():
        return np.zeros(0), None if samples is None else np.zeros(0)
    image_i, image_j = (estimate.find_image_with_name(n) for n in (name_i, name_j))
    camera_i, camera_j = estimate.cameras[image_i.camera_id], estimate.cameras[image_j.camera_id]
    j_from_i = image_j.cam_from_world() * image_i.cam_from_world().inverse()
    lines = epipolar_lines(camera_i, camera_j, j_from_i, pixels[0][0][both])
    rays_j = np.asarray(camera_j.cam_from_img(pixels[1][0][both]))
    distances = np.abs(line_distances(camera_j, lines, np.column_stack([rays_j, np.ones(len(rays_j))])))
    if samples is None:
        return distances, None
    rays_i = np.asarray(camera_i.cam_from_img(pixels[0][0][both]))
    points_i = np.column_stack([rays_i, np.ones(len(rays_i))]) * depths[both, None]
    return distances, band_quantiles(samples, name_i, name_j, camera_j, points_i, lines)
