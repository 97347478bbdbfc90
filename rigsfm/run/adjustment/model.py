"""Small operations on a reconstruction that the adjustment and its covariance share: restore rigs.yaml's
calibration, the fixed-calibration bundle adjustment, outliers, the reprojection noise."""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Sequence

import numpy as np
import pycolmap

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.names import name_of
from rigsfm.core.residuals import reprojection_errors
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.scale import UnusableMeasurement
from rigsfm.run.adjustment.track_baseline import delete_points_without_baseline
from rigsfm.run.options import AdjustOptions


def restore_calibration(reconstruction: pycolmap.Reconstruction, rigs: Sequence[RigCalibration]) -> None:
    """Reset every camera's intrinsics and every narrow ``sensor_from_rig`` to the rigs.yaml values."""
    by_name = {rig.name: rig for rig in rigs}
    for image in reconstruction.images.values():
        name = name_of(image)
        calibration = by_name[name.rig]
        camera = reconstruction.cameras[image.camera_id]
        # pycolmap's stubs: params take an array
        camera.params = calibration.camera(name.sensor).params  # type: ignore[assignment]
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
    # and the tracks of one camera centre (a static rig's frames), whose point COLMAP's angle test keeps at the lens
    return manager.filter_all_points3D(max_error_px, 0.5) + delete_points_without_baseline(reconstruction)


def frames_without_points(reconstruction: pycolmap.Reconstruction) -> list[str]:
    """The registered frames none of whose images observes a 3D point: the rig's name when it is the rig's only
    registered frame, else ``rig frame`` (the frame's image file name), each frame once."""
    frames, observed = {}, set()
    for image_id in reconstruction.reg_image_ids():
        image = reconstruction.image(image_id)
        frames[image.frame_id] = name_of(image)
        if image.num_points3D > 0:
            observed.add(image.frame_id)
    per_rig = Counter(name.rig for name in frames.values())
    return sorted(name.rig if per_rig[name.rig] == 1 else f"{name.rig} {name.frame}"
                  for frame_id, name in frames.items() if frame_id not in observed)


def estimate_pixel_sigma(reconstruction: pycolmap.Reconstruction, max_error_px: float | None = None,
                         without: Collection[int] = ()) -> float:
    """Reprojection noise per image coordinate: ``sqrt(sum e^2 / dof)``, ``dof = 2 N - 3 P - 6 (F - 1)``
    (observations N, points P, frames F); observations above ``max_error_px`` are left out, and so are the points
    ``without`` (point3D ids whose observations have a noise of their own: the pooled noise is the keypoints')."""
    skip = {point_id for point_id in without if reconstruction.exists_point3D(point_id)}
    errors = np.concatenate(list(reprojection_errors(reconstruction, skip).values()) or [np.zeros(0)])
    if max_error_px is not None:
        errors = errors[errors <= max_error_px]
    points = reconstruction.num_points3D() - len(skip)
    dof = 2 * errors.size - 3 * points - 6 * max(reconstruction.num_reg_frames() - 1, 0)
    if dof <= 0:
        raise ReconstructionError("too few observations to estimate the reprojection noise; register more images")
    return float(np.sqrt(np.sum(errors**2) / dof))


def sensor_from_rig_view(reconstruction: pycolmap.Reconstruction, rig_id: int,
                         sensor_id: pycolmap.sensor_t) -> pycolmap.Rigid3d:
    """The rig's own ``sensor_from_rig`` (its ``.params`` is the bundle adjuster's parameter block);
    ``Rig.sensor_from_rig(sensor_id)`` returns a *copy*."""
    # a non-reference sensor has its pose
    return reconstruction.rig(rig_id).non_ref_sensors[sensor_id]  # type: ignore[return-value]


def images_of_camera(reconstruction: pycolmap.Reconstruction, camera: str) -> list[pycolmap.Image]:
    """Registered images of ``<rig>/<sensor>`` or of one image name (as scale.yaml names them)."""
    images = [im for im in reconstruction.images.values()
              if im.has_pose and (im.name == camera or im.name.startswith(camera + "/"))]
    if not images:
        raise UnusableMeasurement(f"{camera} was not registered")
    return sorted(images, key=lambda im: im.image_id)
