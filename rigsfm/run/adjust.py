"""Stage 4: hold every E^sl fixed, bring the network to metric scale, re-run bundle adjustment.

The scale trap: without observations in the narrow images, the mapped world has arbitrary units while
E^sl is metric, and ``Reconstruction.transform(Sim3d)`` scales every ``sensor_from_rig`` too. So: scale
the world to metric first, then restore E^sl (and the calibrated intrinsics) from rigs.yaml, then adjust
with both held constant. Narrow poses then follow as ``narrow_from_wide * wide_from_world``.
"""

from __future__ import annotations

import enum
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.names import name_of
from rigsfm.core.errors import ReconstructionError
from rigsfm.core.residuals import reprojection_errors
from rigsfm.core.rig import RigCalibration
from rigsfm.run.scale import ScaleEstimate, estimate_scale
from rigsfm.run.options import AdjustOptions
from rigsfm.run.scale_file import ScaleSpec

logger = logging.getLogger(__name__)


class ScaleSource(enum.StrEnum):
    MEASUREMENTS = "measurements"  # scale.yaml
    NARROW_BASELINES = "narrow_baselines"  # metric E^sl with observations in narrow images
    NONE = "none"  # arbitrary units


def profile_scale_sigma(reconstruction: pycolmap.Reconstruction, rigs: Sequence[RigCalibration],
                        options: AdjustOptions, step: float = 0.01) -> float:
    """Relative standard uncertainty of a scale set by the metric narrow baselines.

    Profile likelihood: scale the world by 1 +- ``step`` (E^sl restored, everything else re-adjusted),
    and read the scale's variance off the curvature of the total squared reprojection error, with the
    pixel noise estimated from the residuals. Returns inf when the scale is unobservable.
    """

    def squared_error(factor: float) -> tuple[float, int]:
        trial = pycolmap.Reconstruction(reconstruction)
        trial.transform(pycolmap.Sim3d(factor, pycolmap.Rotation3d(), np.zeros(3)))
        restore_calibration(trial, rigs)
        constrained_bundle_adjustment(trial, options, fix_scale=True)
        errors = np.concatenate(list(reprojection_errors(trial).values()))
        return float(np.sum(errors**2)), int(errors.size)

    base, num_observations = squared_error(1.0)
    up, _ = squared_error(1.0 + step)
    down, _ = squared_error(1.0 - step)
    curvature = (up + down - 2.0 * base) / step**2
    noise_variance = base / max(1, num_observations)
    if curvature <= 0 or noise_variance <= 0:
        return float("inf")
    return float(np.sqrt(2.0 * noise_variance / curvature))


@dataclass
class AdjustResult:
    reconstruction: pycolmap.Reconstruction
    scale_source: ScaleSource
    scale: ScaleEstimate | None  # measurements against the final model
    metres_per_mapping_unit: float | None
    mean_reprojection_error_px: float
    scale_relative_sigma: float | None = None  # of a scale set by the narrow baselines


def restore_calibration(reconstruction: pycolmap.Reconstruction, rigs: Sequence[RigCalibration]) -> None:
    """Reset every camera's intrinsics and every narrow ``sensor_from_rig`` to the rigs.yaml values."""
    by_name = {rig.name: rig for rig in rigs}
    for image in reconstruction.images.values():
        name = name_of(image)
        calibration = by_name[name.rig]
        camera = reconstruction.cameras[image.camera_id]
        camera.params = calibration.camera(name.sensor).params
        if name.is_narrow:
            rig = reconstruction.rig(reconstruction.frame(image.frame_id).rig_id)
            rig.set_sensor_from_rig(camera.sensor_id, calibration.narrow_from_wide)


def has_narrow_observations(reconstruction: pycolmap.Reconstruction) -> bool:
    return any(
        image.has_pose and image.num_points3D > 0 and name_of(image).is_narrow
        for image in reconstruction.images.values()
    )


def fixed_calibration_problem(
    reconstruction: pycolmap.Reconstruction,
) -> tuple[pycolmap.BundleAdjustmentOptions, pycolmap.BundleAdjustmentConfig]:
    """BA options and config over every registered rig pose and point, intrinsics and E^sl constant
    (no gauge yet). Shared by the rig-constraint stage and the covariance estimate."""
    ba = pycolmap.BundleAdjustmentOptions(
        refine_focal_length=False,
        refine_principal_point=False,
        refine_extra_params=False,
        refine_sensor_from_rig=False,
        refine_rig_from_world=True,
        refine_points3D=True,
        print_summary=False,
    )
    ba.ceres.use_gpu = False
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.reg_image_ids():
        config.add_image(image_id)
    for camera_id in reconstruction.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    for rig in reconstruction.rigs.values():
        for sensor_id in rig.non_ref_sensors:
            config.set_constant_sensor_from_rig_pose(sensor_id)
    return ba, config


def constrained_bundle_adjustment(
    reconstruction: pycolmap.Reconstruction, options: AdjustOptions, *, fix_scale: bool
) -> float:
    """BA over rig poses and points; intrinsics and E^sl constant; robust loss. Returns mean error (px)."""
    ba, config = fixed_calibration_problem(reconstruction)
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.__members__[options.loss]
    ba.ceres.loss_function_scale = options.loss_scale_px
    solver = ba.ceres.solver_options
    solver.max_num_iterations = options.max_iterations
    solver.function_tolerance = 1e-9
    solver.gradient_tolerance = 1e-10
    solver.parameter_tolerance = 1e-9
    frame_ids = sorted(reconstruction.reg_frame_ids())
    if fix_scale:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    else:  # scale comes from the metric narrow baselines: fix only a rigid motion (one frame)
        config.set_constant_rig_from_world_pose(frame_ids[0])
    summary = pycolmap.create_default_bundle_adjuster(ba, config, reconstruction).solve()
    if not summary.is_solution_usable():
        raise ReconstructionError(f"bundle adjustment with fixed rigs failed: {summary.brief_report()}")
    return float(reconstruction.compute_mean_reprojection_error())


def filter_outliers(reconstruction: pycolmap.Reconstruction, max_error_px: float) -> int:
    manager = pycolmap.ObservationManager(reconstruction)
    return manager.filter_all_points3D(max_error_px, 0.5)


def adjust(
    mapped: pycolmap.Reconstruction,
    rigs: Sequence[RigCalibration],
    scale_spec: ScaleSpec | None,
    options: AdjustOptions | None = None,
) -> AdjustResult:
    """Return a metric reconstruction (a new object) with E^sl and intrinsics exactly as calibrated."""
    options = options or AdjustOptions()
    reconstruction = pycolmap.Reconstruction(mapped)
    if reconstruction.num_reg_frames() < 2:
        raise ReconstructionError("fewer than two rigs were registered; nothing to calibrate")
    narrow_observed = has_narrow_observations(reconstruction)
    scale, metres_per_unit = None, None
    if scale_spec is not None:
        source = ScaleSource.MEASUREMENTS
        # Scale the world (this also scales sensor_from_rig), restore E^sl, adjust with the scale held
        # by the gauge, drop outliers; re-measure and repeat until the scale and the inliers settle.
        scale = estimate_scale(reconstruction, scale_spec)
        metres_per_unit = 1.0
        for _ in range(3):
            metres_per_unit *= scale.metres_per_unit
            reconstruction.transform(pycolmap.Sim3d(scale.metres_per_unit, pycolmap.Rotation3d(), np.zeros(3)))
            restore_calibration(reconstruction, rigs)
            error = constrained_bundle_adjustment(reconstruction, options, fix_scale=True)
            removed = filter_outliers(reconstruction, options.max_reprojection_error_px)
            scale = estimate_scale(reconstruction, scale_spec)
            if removed == 0 and abs(scale.metres_per_unit - 1.0) < 1e-7:
                break
    else:
        source = ScaleSource.NARROW_BASELINES if narrow_observed else ScaleSource.NONE
        if source == ScaleSource.NONE:
            logger.warning("No scale file and no narrow observations: the result is NOT metric")
        restore_calibration(reconstruction, rigs)
        for _ in range(2):
            error = constrained_bundle_adjustment(reconstruction, options, fix_scale=source == ScaleSource.NONE)
            if filter_outliers(reconstruction, options.max_reprojection_error_px) == 0:
                break
    relative_sigma = None
    if source == ScaleSource.NARROW_BASELINES:
        relative_sigma = profile_scale_sigma(reconstruction, rigs, options)
        logger.info("Scale from the narrow baselines: relative uncertainty %.3g", relative_sigma)
    elif scale is not None:
        relative_sigma = scale.sigma / scale.metres_per_unit
    return AdjustResult(reconstruction, source, scale, metres_per_unit, error, relative_sigma)
