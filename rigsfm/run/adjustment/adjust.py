"""Stage 4: the metric bundle adjustment with the rigs' calibration, two ways (``AdjustOptions.calibration``).

``REFINE`` (default): one adjustment that uses everything the user knows, each with its weight. COLMAP's own
bundle adjuster (``pycolmap.create_default_ceres_bundle_adjuster``) over every registered rig pose and point,
with the intrinsics and every observed narrow ``sensor_from_rig`` (E^sl) refined; on its Ceres problem:

- a Gaussian prior on every camera's params at rigs.yaml's values (``pyceres.factors.NormalPrior``), sigmas
  from ``rigsfm.run.adjustment.priors``; a sigma of 0 holds that parameter (``pyceres.SubsetManifold``);
- COLMAP's pose prior (``pycolmap.cost_functions.AbsolutePosePriorCost``) on every E^sl block;
- every scale.yaml camera distance as a residual between camera centres (``costs.CameraDistanceCost``; a narrow
  centre through its E^sl), every known length as its two end points observed in their images
  (``ReprojErrorCost`` / ``RigReprojErrorCost`` with the file's pixel sigma) tied by ``costs.LengthCost``;
- COLMAP's robust loss on the reprojection residuals, outliers dropped between rounds.

Then each rig's refinement is tested (:func:`hold_or_refine`: the images must inform some direction of the network's
calibration more than rigs.yaml's sigmas do, and a rig's change must be consistent with the information they give
about it); a rig that fails is held at rigs.yaml's values and the network adjusted again; with every rig held, and
the network's shape fixed by the images, the adjustment is ``FIXED``'s. On a weak network (two rigs registered from
a few dozen clicks) the images cannot inform the calibration, and refining it anyway moved the narrow cameras further
from the truth than holding it.

A parameter no image observes (intrinsics and E^sl of a narrow camera without points) is not in COLMAP's problem:
it stays at rigs.yaml's value, and its prior enters the covariance as an independent block. Residuals are whitened
and in pixels: priors and measurements are multiplied by the images' weighting noise (the estimated reprojection
noise times ``pixel_sigma_inflation``). Gauge: one frame held when the scale is observed (measurements, or metric
E^sl baselines with narrow observations), else COLMAP's TWO_CAMS_FROM_WORLD (which also holds the scale).
Solved with ``pyceres.solve``: ``CeresBundleAdjuster.solve`` holds the GIL, and a Ceres worker thread that
evaluates one of the Python measurement costs would wait for it forever.

``FIXED`` (``--fixed-calibration``, rigsfm's stage before issue 13): hold every E^sl and intrinsic exactly, bring
the network to metric scale with one similarity scale fitted to the measurements, re-run bundle adjustment.

The scale trap (both): without observations in the narrow images, the mapped world has arbitrary units while E^sl
is metric, and ``Reconstruction.transform(Sim3d)`` scales every ``sensor_from_rig`` too. So: scale the world to
metric first, then restore E^sl (and the calibrated intrinsics) from rigs.yaml, then adjust. Narrow poses then
follow as ``narrow_from_wide * wide_from_world``.
"""

from __future__ import annotations

import enum
import logging
import time
from collections import Counter
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import pyceres
import pycolmap
import pycolmap.cost_functions  # not imported by ``import pycolmap``
import scipy.linalg

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.names import name_of
from rigsfm.core.residuals import reprojection_errors
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.costs import CameraDistanceCost, CentreTerm, LengthCost, skew
from rigsfm.run.adjustment.priors import CalibrationPriors, calibration_priors, pose_prior_residual_covariance
from rigsfm.run.adjustment.scale import (
    Measurement,
    ScaleEstimate,
    UnusableMeasurement,
    estimate_scale,
    triangulate_in_images,
)
from rigsfm.run.checks.diagnostics import loosely_tied_rigs
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.options import AdjustOptions, Calibration

if TYPE_CHECKING:
    from rigsfm.run.adjustment.uncertainty import JointCovariance

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


class Gauge(enum.StrEnum):
    RIGID = "rigid"  # one frame held; the scale is observed
    TWO_CAMS_FROM_WORLD = "two_cams_from_world"  # COLMAP's: one frame and one coordinate of a second


@dataclass
class AdjustResult:
    reconstruction: pycolmap.Reconstruction
    scale_source: ScaleSource
    scale: ScaleEstimate | None  # measurements against the final model
    metres_per_mapping_unit: float | None
    mean_reprojection_error_px: float
    scale_relative_sigma: float | None = None  # of a scale set by the narrow baselines; REFINE: of the network's size
    calibration: Calibration = Calibration.FIXED
    gauge: Gauge = Gauge.TWO_CAMS_FROM_WORLD  # of the adjustment (and of its covariance)
    rigs: tuple[RigCalibration, ...] = ()  # the calibration file the adjustment started from
    priors: CalibrationPriors | None = None
    scale_spec: ScaleSpec | None = None
    options: AdjustOptions = field(default_factory=AdjustOptions)
    pixel_sigma: float | None = None  # REFINE: estimated reprojection noise (px per image coordinate)
    rounds: int = 0
    seconds: float = 0.0
    covariance: JointCovariance | None = None  # rigsfm.run.adjustment.uncertainty.joint_covariance, once computed
    held_rigs: frozenset[str] = frozenset()  # REFINE: rigs whose calibration was held at rigs.yaml's (hold_or_refine)
    decisions: list[CalibrationDecision] = field(default_factory=list)  # REFINE: per rig, held or refined and why
    warnings: list[str] = field(default_factory=list)  # for the run's summary


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
    return manager.filter_all_points3D(max_error_px, 0.5)


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


def adjust(
    mapped: pycolmap.Reconstruction,
    rigs: Sequence[RigCalibration],
    scale_spec: ScaleSpec | None,
    options: AdjustOptions | None = None,
    priors: CalibrationPriors | None = None,
    *,
    with_covariance: bool = True,
    held_rigs: Collection[str] | None = None,
) -> AdjustResult:
    """A metric reconstruction (a new object; ``mapped`` is not modified), its calibration refined with
    ``priors`` (default: ``calibration_priors(rigs)``, a good board's) or held (``options.calibration``).
    ``with_covariance``: a refined metric result carries its joint covariance (and the scale's sigma from it).
    ``held_rigs``: refining, hold these rigs' calibration instead of testing each rig's (:func:`hold_or_refine`)."""
    options = options or AdjustOptions()
    start = time.perf_counter()
    if options.calibration == Calibration.REFINE:
        result = _adjust_refined(mapped, rigs, scale_spec, options, priors or calibration_priors(rigs),
                                 with_covariance, held_rigs)
    else:
        result = _adjust_fixed(mapped, rigs, scale_spec, options)
        result.priors, result.scale_spec, result.options = priors, scale_spec, options
    result.rigs = tuple(rigs)
    result.seconds = time.perf_counter() - start
    return result


def _adjust_fixed(mapped: pycolmap.Reconstruction, rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None,
                  options: AdjustOptions) -> AdjustResult:
    """Today's stage: E^sl and intrinsics exactly as calibrated."""
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
    gauge = Gauge.RIGID if source == ScaleSource.NARROW_BASELINES else Gauge.TWO_CAMS_FROM_WORLD
    return AdjustResult(reconstruction, source, scale, metres_per_unit, error, relative_sigma,
                        calibration=Calibration.FIXED, gauge=gauge)


# ------------------------------------------------------------------------------------------------------------
# REFINE: the adjustment with calibration priors and measurement residuals


def estimate_pixel_sigma(reconstruction: pycolmap.Reconstruction, max_error_px: float | None = None) -> float:
    """Reprojection noise per image coordinate: ``sqrt(sum e^2 / dof)``, ``dof = 2 N - 3 P - 6 (F - 1)``
    (observations N, points P, frames F); observations above ``max_error_px`` are left out."""
    errors = np.concatenate(list(reprojection_errors(reconstruction).values()) or [np.zeros(0)])
    if max_error_px is not None:
        errors = errors[errors <= max_error_px]
    dof = 2 * errors.size - 3 * reconstruction.num_points3D() - 6 * max(reconstruction.num_reg_frames() - 1, 0)
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


@dataclass
class _Measurement:
    kind: str
    label: str
    meters: float
    sigma: float  # of the measurement, plus what constant (unobserved) E^sl adds to it (metres)
    length: Callable[..., float]  # () -> metres in the current model


class JointProblem:
    """COLMAP's bundle adjuster over ``reconstruction`` (changed in place by :meth:`solve`) with intrinsics and
    observed E^sl refined, plus priors (unless ``with_priors`` is False: then the calibration is in the problem,
    for its Jacobian, but only sigma-0 parameters are held) and measurements. Keeps the Python cost functions
    and the known lengths' end points alive as long as the problem."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, rigs: Sequence[RigCalibration],
                 priors: CalibrationPriors, scale_spec: ScaleSpec | None, options: AdjustOptions,
                 pixel_sigma: float, *, gauge: Gauge, robust: bool, with_priors: bool = True,
                 held_rigs: frozenset[str] = frozenset(), consider_held: bool = False):
        self.reconstruction = reconstruction
        # held_rigs: their intrinsics and E^sl stay at rigs.yaml's values (constant blocks); with consider_held they
        # are variable but without prior, for the Jacobian of the covariance that considers their prior
        self.held_rigs = frozenset(held_rigs)
        self.consider_held = consider_held
        self.priors = priors
        self.weight_sigma = float(pixel_sigma) * options.pixel_sigma_inflation  # the images' weighting noise
        self.gauge = gauge
        self.settle_chi2: float | None = None  # solve: stop once less than this chi^2 is left to gain (SettledStop)
        self.calibration = {rig.name: rig for rig in rigs}
        self._keep: list = []  # cost functions and blocks the C++ problem refers to
        self.end_points: list[np.ndarray] = []
        self.measurements: list[_Measurement] = []
        self.unused: list[str] = []
        self.camera_names = {im.camera_id: name_of(im) for im in reconstruction.images.values()}

        ba = pycolmap.BundleAdjustmentOptions(
            refine_focal_length=True, refine_principal_point=True, refine_extra_params=True,
            refine_sensor_from_rig=True, refine_rig_from_world=True, refine_points3D=True, print_summary=False)
        ba.ceres.use_gpu = False
        if robust:
            ba.ceres.loss_function_type = pycolmap.LossFunctionType.__members__[str(options.loss)]
            ba.ceres.loss_function_scale = options.loss_scale_px
        else:
            ba.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
        solver = ba.ceres.solver_options
        solver.max_num_iterations = options.max_iterations
        solver.function_tolerance = 1e-9
        solver.gradient_tolerance = 1e-10
        solver.parameter_tolerance = 1e-9
        self.ba_options = ba
        self.config = pycolmap.BundleAdjustmentConfig()
        for image_id in reconstruction.reg_image_ids():
            self.config.add_image(image_id)
        self.frame_ids = sorted(reconstruction.reg_frame_ids())
        self.fixed_frame_id = self.frame_ids[0]
        if gauge == Gauge.RIGID:
            self.config.set_constant_rig_from_world_pose(self.fixed_frame_id)
        else:
            self.config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        self.adjuster = pycolmap.create_default_ceres_bundle_adjuster(ba, self.config, reconstruction)
        self.problem: pyceres.Problem = self.adjuster.problem
        self.subset_frame = self._two_cams_subset() if gauge == Gauge.TWO_CAMS_FROM_WORLD else None
        if not consider_held:
            self._hold_rigs()
        if scale_spec is not None:
            self._add_camera_distances(scale_spec)
            self._add_known_lengths(scale_spec)
        self._add_camera_priors(with_priors)
        if with_priors:
            self._add_sensor_priors()

    # -- blocks ----------------------------------------------------------------------------------------------
    def has_variable(self, block: np.ndarray) -> bool:
        return self.problem.has_parameter_block(block) and not self.problem.is_parameter_block_constant(block)

    def frame_block(self, frame_id: int) -> np.ndarray:
        # registered frames have their poses
        return self.reconstruction.frame(frame_id).rig_from_world.params  # type: ignore[union-attr]

    def narrow_sensors(self):
        """``(rig_id, sensor_id, camera_id, rig name)`` of every non-reference sensor with registered images."""
        for rig_id, rig in self.reconstruction.rigs.items():
            for sensor_id in rig.non_ref_sensors:
                name = self.camera_names.get(sensor_id.id)
                if name is not None and sensor_id.id in self.reconstruction.cameras:
                    yield rig_id, sensor_id, sensor_id.id, name.rig

    def camera_sigmas(self, camera_id: int) -> np.ndarray:
        name = self.camera_names[camera_id]
        return self.priors[name.rig].sensor(name.sensor)

    def _two_cams_subset(self) -> tuple[int, int] | None:
        """The (frame, translation coordinate) COLMAP's TWO_CAMS_FROM_WORLD gauge holds besides the first frame
        (its own choice replicated: the first reference image with points, then the first reference image of
        another frame with a non-zero baseline, its largest coordinate); checked against the block's tangent."""
        rec = self.reconstruction
        first = None
        for image_id in sorted(rec.reg_image_ids()):
            image = rec.image(image_id)
            if not image.is_ref_in_frame() or image.num_points3D == 0:
                continue
            if first is None:
                first = image
                continue
            if image.frame_id == first.frame_id or not self.problem.has_parameter_block(self.frame_block(image.frame_id)):
                continue
            # registered frames have their poses
            baseline = np.asarray((rec.frame(first.frame_id).rig_from_world  # type: ignore[operator]
                                   * rec.frame(image.frame_id).rig_from_world.inverse()).translation)  # type: ignore[union-attr]
            if np.abs(baseline).max() > 1e-9:
                frame_id, dim = image.frame_id, int(np.argmax(np.abs(baseline)))
                if self.problem.parameter_block_tangent_size(self.frame_block(frame_id)) != 5:
                    raise ReconstructionError("could not identify COLMAP's TWO_CAMS_FROM_WORLD gauge")
                self.fixed_frame_id = first.frame_id
                return frame_id, dim
        return None

    # -- measurements ----------------------------------------------------------------------------------------
    def _centre_terms(self, camera: str, blocks: list[np.ndarray]) -> tuple[list[CentreTerm], np.ndarray]:
        """Centre terms of a scale.yaml camera (appending the blocks they need to ``blocks``), and the 3x3
        covariance its centre inherits from constant (unobserved) E^sl priors."""
        terms, extra = [], np.zeros((3, 3))
        images = images_of_camera(self.reconstruction, camera)

        def index(block: np.ndarray) -> int:
            for k, b in enumerate(blocks):
                if b.__array_interface__["data"][0] == block.__array_interface__["data"][0]:
                    return k
            if not self.problem.has_parameter_block(block):  # a frame no point ties: constant
                self.problem.add_parameter_block(block, 7)
                self.problem.set_parameter_block_constant(block)
            blocks.append(block)
            return len(blocks) - 1

        for image in images:
            frame = self.reconstruction.frame(image.frame_id)
            # registered frames have their poses
            rig_index = index(frame.rig_from_world.params)  # type: ignore[union-attr]
            if image.is_ref_in_frame():
                terms.append(CentreTerm(rig_index))
                continue
            sensor = sensor_from_rig_view(self.reconstruction, frame.rig_id,
                                          self.reconstruction.cameras[image.camera_id].sensor_id)
            if self.has_variable(sensor.params):
                terms.append(CentreTerm(rig_index, sensor=index(sensor.params)))
                continue
            # a non-reference sensor has its pose
            terms.append(CentreTerm(rig_index, sensor_from_rig=pycolmap.Rigid3d(sensor)))  # type: ignore[call-overload]
            cov = self.priors[name_of(image).rig].narrow_from_wide
            r = frame.rig_from_world.rotation.matrix()  # type: ignore[union-attr]  # registered frames have their poses
            r_e, t_e = sensor.rotation.matrix(), np.asarray(sensor.translation)
            jac = np.hstack([-r.T @ r_e.T @ skew(t_e), -r.T @ r_e.T]) / len(images)  # d centre / d [w, dt] of E^sl
            extra += jac @ cov @ jac.T
        return terms, extra

    def _add_camera_distances(self, spec: ScaleSpec) -> None:
        for d in spec.camera_distances:
            label = f"{d.a} - {d.b}"
            blocks: list[np.ndarray] = []
            try:
                terms_a, extra_a = self._centre_terms(d.a, blocks)
                terms_b, extra_b = self._centre_terms(d.b, blocks)
            except UnusableMeasurement as why:
                self.unused.append(f"{label}: {why}")
                continue
            probe = CameraDistanceCost(terms_a, terms_b, len(blocks), d.meters, 1.0, 1.0)
            (c_a, _), (c_b, _) = probe.centres(blocks, with_jacobians=False)
            u = (c_a - c_b) / max(np.linalg.norm(c_a - c_b), 1e-12)
            sigma = float(np.sqrt(d.sigma**2 + u @ (extra_a + extra_b) @ u))
            cost = CameraDistanceCost(terms_a, terms_b, len(blocks), d.meters, sigma, self.weight_sigma)
            self.problem.add_residual_block(cost, None, blocks)
            self._keep.append(cost)

            def length(cost=cost, blocks=blocks) -> float:
                (a, _), (b, _) = cost.centres(blocks, with_jacobians=False)
                return float(np.linalg.norm(a - b))

            self.measurements.append(_Measurement("camera_distance", label, d.meters, sigma, length))

    def _add_known_lengths(self, spec: ScaleSpec) -> None:
        rec = self.reconstruction
        by_name = {im.name: im for im in rec.images.values() if im.has_pose}
        for i, item in enumerate(spec.known_lengths):
            label = f"known_length[{i}]"
            observations = [(by_name[o.image], o) for o in item.observations if o.image in by_name]
            ends = []
            for end in ("a", "b"):
                xyz = triangulate_in_images(rec, [(image, np.asarray(getattr(o, end), dtype=np.float64))
                                                  for image, o in observations])
                ends.append(None if xyz is None else np.array(xyz, dtype=np.float64))
            if any(e is None for e in ends):
                self.unused.append(f"{label} ({item.meters} m): fewer than two of its images were registered")
                continue
            self.end_points.extend(ends)  # type: ignore[arg-type]  # both ends seen: checked above
            point_cov = (spec.pixel_sigma / self.weight_sigma) ** 2 * np.eye(2)
            for image, o in observations:
                camera = rec.cameras[image.camera_id]
                frame = rec.frame(image.frame_id)
                # registered frames have their poses
                if not self.problem.has_parameter_block(frame.rig_from_world.params):  # type: ignore[union-attr]
                    self.problem.add_parameter_block(frame.rig_from_world.params, 7)  # type: ignore[union-attr]
                    self.problem.set_parameter_block_constant(frame.rig_from_world.params)  # type: ignore[union-attr]
                if not self.problem.has_parameter_block(camera.params):
                    self.problem.add_parameter_block(camera.params, len(camera.params))
                    self.problem.set_parameter_block_constant(camera.params)
                for end, xyz in zip(("a", "b"), ends, strict=True):
                    xy = np.asarray(getattr(o, end), dtype=np.float64)
                    if image.is_ref_in_frame():
                        cost = pycolmap.cost_functions.ReprojErrorCost(camera.model, point_cov, xy)
                        # registered frames have their poses
                        blocks = [xyz, frame.rig_from_world.params, camera.params]  # type: ignore[union-attr]
                    else:
                        sensor = sensor_from_rig_view(rec, frame.rig_id, camera.sensor_id)
                        if self.has_variable(sensor.params):
                            cost = pycolmap.cost_functions.RigReprojErrorCost(camera.model, point_cov, xy)
                            # registered frames have their poses
                            blocks = [xyz, sensor.params, frame.rig_from_world.params, camera.params]  # type: ignore[union-attr]
                        else:
                            cost = pycolmap.cost_functions.RigReprojErrorCost(camera.model, point_cov, xy,
                                                                              # a non-reference sensor has its pose
                                                                              pycolmap.Rigid3d(sensor))  # type: ignore[call-overload]
                            # registered frames have their poses
                            blocks = [xyz, frame.rig_from_world.params, camera.params]  # type: ignore[union-attr]
                    self.problem.add_residual_block(cost, None, blocks)
                    self._keep.append(cost)
            cost = LengthCost(item.meters, item.sigma, self.weight_sigma)
            self.problem.add_residual_block(cost, None, ends)
            self._keep.append(cost)
            self.measurements.append(_Measurement("known_length", label, item.meters, item.sigma,
                                                  lambda ends=ends: float(np.linalg.norm(ends[0] - ends[1]))))

    # -- priors ----------------------------------------------------------------------------------------------
    def _hold_rigs(self) -> None:
        """The held rigs' camera and E^sl blocks constant (before the measurements, which then carry a held E^sl's
        prior in their sigma as for an unobserved one)."""
        for camera_id, camera in self.reconstruction.cameras.items():
            name = self.camera_names.get(camera_id)
            if name is not None and name.rig in self.held_rigs and self.has_variable(camera.params):
                self.problem.set_parameter_block_constant(camera.params)
        for rig_id, sensor_id, _, rig_name in self.narrow_sensors():
            block = sensor_from_rig_view(self.reconstruction, rig_id, sensor_id).params
            if rig_name in self.held_rigs and self.has_variable(block):
                self.problem.set_parameter_block_constant(block)

    def _add_camera_priors(self, with_priors: bool) -> None:
        for camera_id, camera in self.reconstruction.cameras.items():
            block = camera.params
            if camera_id not in self.camera_names or not self.has_variable(block):
                continue
            sigmas = self.camera_sigmas(camera_id)
            held = np.flatnonzero(sigmas == 0)
            if len(held) == len(sigmas):
                self.problem.set_parameter_block_constant(block)
                continue
            if len(held):
                self.problem.set_manifold(block, pyceres.SubsetManifold(len(sigmas), held.tolist()))
            name = self.camera_names[camera_id]
            if not with_priors or name.rig in self.held_rigs:
                continue
            mean = np.asarray(self.calibration[name.rig].camera(name.sensor).params, dtype=np.float64)
            variances = np.where(sigmas > 0, sigmas, 1.0) ** 2 / self.weight_sigma**2  # held: any (no effect)
            cost = pyceres.factors.NormalPrior(mean, np.diag(variances))
            self.problem.add_residual_block(cost, None, [block])
            self._keep.append(cost)

    def _add_sensor_priors(self) -> None:
        for rig_id, sensor_id, _, rig_name in self.narrow_sensors():
            block = sensor_from_rig_view(self.reconstruction, rig_id, sensor_id).params
            if not self.has_variable(block) or rig_name in self.held_rigs:
                continue
            prior = self.calibration[rig_name].narrow_from_wide
            cov = pose_prior_residual_covariance(self.priors[rig_name].narrow_from_wide, prior) / self.weight_sigma**2
            cost = pycolmap.cost_functions.AbsolutePosePriorCost(cov, prior)
            self.problem.add_residual_block(cost, None, [block])
            self._keep.append(cost)

    # -- solve -----------------------------------------------------------------------------------------------
    def solve(self) -> pyceres.SolverSummary:
        """COLMAP's solver options (its choice of linear solver by problem size) with ``pyceres.solve``, which
        releases the GIL (see the module docstring)."""
        solver = self.ba_options.ceres.create_solver_options(self.config, self.problem)
        solver.minimizer_progress_to_stdout = False
        solver.logging_type = pyceres.LoggingType.SILENT
        if self.settle_chi2 is not None:  # COLMAP binds a copy of pyceres' SolverOptions without ``callbacks``
            solver = pyceres.SolverOptions(solver.todict())
            solver.callbacks = [SettledStop(self.settle_chi2 * self.weight_sigma**2 / 2.0 / SETTLE_STEPS)]
        summary = pyceres.SolverSummary()
        pyceres.solve(solver, self.problem, summary)
        if summary.termination_type == pyceres.TerminationType.FAILURE or not np.isfinite(summary.final_cost):
            raise ReconstructionError(f"bundle adjustment with calibration priors failed: {summary.BriefReport()}")
        return summary

    def stop_as(self, *, final: bool) -> None:
        """Where :meth:`solve` stops: a round's (``ROUND_FUNCTION_TOLERANCE``) or the result's
        (``FINAL_FUNCTION_TOLERANCE``, and :class:`SettledStop` with ``FINAL_SETTLE_CHI2`` left to gain)."""
        self.ba_options.ceres.solver_options.function_tolerance = (
            FINAL_FUNCTION_TOLERANCE if final else ROUND_FUNCTION_TOLERANCE)
        self.settle_chi2 = FINAL_SETTLE_CHI2 if final else None

    def solve_to_convergence(self) -> pyceres.SolverSummary:
        """:meth:`solve` again (up to ``MAX_SOLVES_PER_ROUND`` times) while Ceres stops at its iteration limit."""
        for _ in range(MAX_SOLVES_PER_ROUND):
            summary = self.solve()
            if summary.termination_type != pyceres.TerminationType.NO_CONVERGENCE:
                break
        return summary

    def scale_estimate(self) -> ScaleEstimate | None:
        """The measurements against the current model, as a ``ScaleEstimate`` of 1 metre per unit (they are
        inside the adjustment: no scale is fitted afterwards)."""
        if not self.measurements and not self.unused:
            return None
        rows = tuple(Measurement(m.kind, m.label, m.meters, m.length(), m.sigma) for m in self.measurements)
        return ScaleEstimate(1.0, float("nan"), rows, tuple(self.unused))


class SettledStop(pyceres.IterationCallback):
    """Ends a solve at the first successful step that gains less than ``cost``. With the robust loss,
    Levenberg-Marquardt creeps near the minimum (64 rigs: 60-80 steps of ~1 s, each gaining 0.93-0.95 times the
    last; the squared loss converges in 6): the steps still to come then gain at most ~``SETTLE_STEPS`` times the
    last one. The cost is ``weight_sigma**2 / 2`` times the chi^2 of the whitened residuals, and the chi^2 left to
    gain bounds every derived quantity's distance to the optimum: at most ``sqrt(chi2)`` of its reported sigma."""

    def __init__(self, cost: float):
        super().__init__()
        self.cost = float(cost)

    def __call__(self, summary: pyceres.IterationSummary) -> pyceres.CallbackReturnType:
        if summary.iteration > 0 and summary.step_is_successful and 0.0 <= summary.cost_change < self.cost:
            return pyceres.CallbackReturnType.SOLVER_TERMINATE_SUCCESSFULLY
        return pyceres.CallbackReturnType.SOLVER_CONTINUE


@dataclass(frozen=True)
class CalibrationDecision:
    """One rig's calibration after :func:`hold_or_refine`: ``held`` at rigs.yaml's values or refined, and why."""

    rig: str
    held: bool
    reason: str  # one clause
    largest_gain: float = 0.0  # the largest share of one direction's prior variance the images removed (this rig)
    chi2: float = 0.0  # the refinement's change against the spread the images explain (consistency test)
    dof: int = 0
    limit: float = 0.0  # the chi-square's HOLD_QUANTILE quantile


@dataclass(frozen=True)
class _CalibrationChange:
    """The refined-minus-rigs.yaml change of the observed calibration (the covariance's tangent), over the parameters
    with a non-zero prior sigma: ``delta``, the prior and posterior covariances, and each coordinate's rig."""

    delta: np.ndarray
    prior: np.ndarray
    posterior: np.ndarray
    rigs: np.ndarray


def _calibration_change(result: AdjustResult, covariance: JointCovariance) -> _CalibrationChange:
    rec, priors = result.reconstruction, result.priors
    calibration = {r.name: r for r in result.rigs}
    keys, changes, prior_blocks, owners = [], [], [], []
    for image in sorted(rec.images.values(), key=lambda im: im.image_id):
        name = name_of(image)
        if not image.has_pose or name.rig not in calibration:
            continue
        key = ("camera", image.camera_id)
        if key in covariance.offsets and key not in covariance.prior_only and key not in keys:
            keys.append(key)
            changes.append(np.asarray(rec.cameras[image.camera_id].params)
                           - np.asarray(calibration[name.rig].camera(name.sensor).params))
            # priors are set with covariance
            prior_blocks.append(np.diag(priors[name.rig].sensor(name.sensor) ** 2))  # type: ignore[index]
            owners += [name.rig] * len(changes[-1])
        key = ("sensor_from_rig", image.camera_id)
        if name.is_narrow and key in covariance.offsets and key not in covariance.prior_only and key not in keys:
            keys.append(key)
            sensor = sensor_from_rig_view(rec, rec.frame(image.frame_id).rig_id, rec.cameras[image.camera_id].sensor_id)
            given = calibration[name.rig].narrow_from_wide
            turn = sensor.rotation * given.rotation.inverse()  # R = Exp(w) R_yaml: w is its rotation vector
            quat = np.asarray(turn.quat)  # x, y, z, w
            axis = quat[:3] / max(float(np.linalg.norm(quat[:3])), 1e-300) * (1.0 if quat[3] >= 0 else -1.0)
            changes.append(np.r_[axis * turn.angle(), np.asarray(sensor.translation) - np.asarray(given.translation)])
            # priors are set with covariance
            prior_blocks.append(priors[name.rig].narrow_from_wide)  # type: ignore[index]
            owners += [name.rig] * 6
    size = sum(len(c) for c in changes)
    prior = np.zeros((size, size))
    at = 0
    for block in prior_blocks:
        prior[at:at + len(block), at:at + len(block)] = block
        at += len(block)
    keep = np.diag(prior) > 0  # sigma 0: held exactly by the prior itself
    posterior = covariance.sub(keys) if keys else np.zeros((0, 0))
    delta = np.concatenate(changes) if changes else np.zeros(0)
    return _CalibrationChange(delta[keep], prior[np.ix_(keep, keep)], posterior[np.ix_(keep, keep)],
                              np.asarray(owners, dtype=object)[keep])


def _gains(prior: np.ndarray, posterior: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The share ``g_k`` of the prior variance the images removed along each eigen-direction of ``I - Q`` (``Q`` the
    posterior in the prior's whitened coordinates) and the whitened change's coordinates along them."""
    inverse = scipy.linalg.solve_triangular(np.linalg.cholesky(prior), np.eye(len(prior)), lower=True)
    gains, vectors = np.linalg.eigh(np.eye(len(prior)) - inverse @ posterior @ inverse.T)
    return gains, vectors.T @ (inverse @ delta)


def hold_or_refine(result: AdjustResult, covariance: JointCovariance | None) -> list[CalibrationDecision]:
    """Per rig, whether its refined calibration is kept or held at rigs.yaml's values.

    In the prior's whitened coordinates (``u = L^-1 (c - c_yaml)``, ``Sigma = L L^T``) the images remove a share
    ``g_k`` of the prior variance along each eigen-direction ``v_k`` of ``I - L^-1 P L^-T`` (``P`` the posterior
    covariance). Three tests:

    - the network's observability: refine only if some direction of the whole calibration (over all rigs: the
      images inform combinations, such as two rigs' focal lengths against each other) has ``g_k >= 1/2``, i.e. the
      images inform it more than rigs.yaml's sigmas do; below that the posterior is mostly the prior, and a change
      is mostly whatever the images' unmodelled errors (wrong clicks, systematic feature offsets) pulled it to;
    - each rig's observability: ``g_k >= MIN_GAIN`` in some direction of its own calibration (its marginal);
    - each rig's consistency: were priors and images both right, its change would be distributed as ``N(0, I - Q)``
      (the spread of the posterior mean), so ``sum_k (v_k . u)^2 / g_k`` over its directions with ``g_k >=
      MIN_GAIN`` is chi-square with that many degrees of freedom; above the ``HOLD_QUANTILE`` quantile the images
      moved the calibration further than their information allows, and the move is not trusted.

    Without a covariance (a rank-deficient problem) every rig is held."""
    from scipy.stats import chi2 as chi2_distribution  # scipy.stats takes a while to import

    rigs = sorted({name_of(im).rig for im in result.reconstruction.images.values() if im.has_pose}
                  & {r.name for r in result.rigs})
    if covariance is None:
        return [CalibrationDecision(rig, True, "no covariance to test its refinement against") for rig in rigs]
    change = _calibration_change(result, covariance)
    network_gain = float(_gains(change.prior, change.posterior, change.delta)[0].max(initial=0.0)) \
        if len(change.delta) else 0.0
    decisions = []
    for rig in rigs:
        mine = change.rigs == rig
        if not mine.any():
            decisions.append(CalibrationDecision(rig, True, "no image observes its calibration"))
            continue
        gains, z = _gains(change.prior[np.ix_(mine, mine)], change.posterior[np.ix_(mine, mine)], change.delta[mine])
        tested = gains >= MIN_GAIN
        chi2, dof = float(np.sum(z[tested] ** 2 / gains[tested])), int(tested.sum())
        limit = float(chi2_distribution.ppf(HOLD_QUANTILE, dof)) if dof else 0.0
        largest = float(gains.max())
        if network_gain < 0.5:
            held, reason = True, (f"the images inform no direction of the network's calibration more than rigs.yaml's "
                                  f"sigmas do (they remove at most {int(100 * max(network_gain, 0.0))} % of one's prior "
                                  "variance)")
        elif not dof:
            held, reason = True, (f"the images barely observe its calibration (at most {int(100 * max(largest, 0.0))} % "
                                  "of a direction's prior variance removed)")
        elif chi2 > limit:
            held, reason = True, (f"the refinement moved it further than the images' information allows (chi-square "
                                  f"{chi2:.1f} > {limit:.1f}, {dof} dof)")
        else:
            held, reason = False, (f"the images inform it (up to {100 * largest:.0f} % of a direction's prior variance "
                                   f"removed) and agree with rigs.yaml (chi-square {chi2:.1f} <= {limit:.1f}, {dof} dof)")
        decisions.append(CalibrationDecision(rig, held, reason, largest, chi2, dof, limit))
    return decisions


# Directions whose prior variance the images reduce by less are left out of the consistency test: the final solve
# stops with up to FINAL_SETTLE_CHI2 (0.04) of chi^2 left to gain, which adds up to 0.04 / g to the test along a
# direction of gain g (0.4 at this floor), and a rig none of whose directions reaches it is barely observed.
MIN_GAIN = 0.1
HOLD_QUANTILE = 0.95  # of the consistency test


def _choose_gauge(reconstruction: pycolmap.Reconstruction, scale_spec: ScaleSpec | None) -> tuple[ScaleSource, Gauge]:
    if scale_spec is not None and (scale_spec.camera_distances or scale_spec.known_lengths):
        return ScaleSource.MEASUREMENTS, Gauge.RIGID
    if has_narrow_observations(reconstruction):
        return ScaleSource.NARROW_BASELINES, Gauge.RIGID
    logger.warning("No scale file and no narrow observations: the result is NOT metric")
    return ScaleSource.NONE, Gauge.TWO_CAMS_FROM_WORLD


def _metres_per_mapping_unit(mapped: pycolmap.Reconstruction, adjusted: pycolmap.Reconstruction) -> float | None:
    """Ratio of the registered frames' spread after and before (RMS distance of the wide centres to their mean)."""
    def spread(rec: pycolmap.Reconstruction) -> np.ndarray:
        # registered frames have their poses
        return np.array([rec.frame(f).rig_from_world.inverse().translation for f in sorted(adjusted.reg_frame_ids())])  # type: ignore[union-attr]

    before, after = spread(mapped), spread(adjusted)
    size = float(np.sqrt(np.mean(np.sum((before - before.mean(axis=0)) ** 2, axis=1))))
    return None if size <= 0 else float(np.sqrt(np.mean(np.sum((after - after.mean(axis=0)) ** 2, axis=1)))) / size


MAX_SOLVES_PER_ROUND = 5
ROUND_FUNCTION_TOLERANCE = 1e-6  # the rounds (outliers, pixel noise)
FINAL_FUNCTION_TOLERANCE = 1e-9  # the result
FINAL_SETTLE_CHI2 = 0.04  # the result: stop with less than this chi^2 left to gain (0.2 sigma; SettledStop)
SETTLE_STEPS = 20  # a creeping solve's remaining steps gain at most ~20 times its last (SettledStop)
# A robust round that drops at most this share of the observations, with the pixel noise settled, is the last
# (the final solve goes on without them). Full-size circles: 16 rigs dropped 0, 72 (0.14 %), 4 (0.008 %), 0 of
# ~53 000 in their four rounds, 64 rigs 28, 562 (0.2 %), 32 (0.011 %), 4 of ~287 000; the fourth round took 1 and
# 16 s.
NEGLIGIBLE_DROP = 1e-3


def _adjust_refined(mapped: pycolmap.Reconstruction, rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None,
                    options: AdjustOptions, priors: CalibrationPriors, with_covariance: bool = True,
                    held_rigs: Collection[str] | None = None) -> AdjustResult:
    """Every rig's calibration refined, then each rig's refinement tested (:func:`hold_or_refine`); the rigs whose
    refinement fails are held at rigs.yaml's values and the network adjusted again (every rig held in a network whose
    shape the images fix: the result is ``--fixed-calibration``'s, its ``calibration`` FIXED). ``held_rigs`` given: those
    held, no test (the sampled band's draws repeat the estimate's choice)."""
    from rigsfm.run.adjustment.uncertainty import joint_covariance, network_size_sigma

    result = _refine(mapped, rigs, scale_spec, options, priors, frozenset(held_rigs or ()))
    if held_rigs is None and result.scale_source != ScaleSource.NONE:
        result.covariance = joint_covariance(result)
        result.decisions = hold_or_refine(result, result.covariance)
        held = frozenset(d.rig for d in result.decisions if d.held)
        for decision in result.decisions:
            logger.info("Calibration of %s %s: %s", decision.rig, "held at rigs.yaml" if decision.held else "refined",
                        decision.reason)
        decisions, warnings = result.decisions, result.warnings  # the refined pass's warnings stay true of the input
        # Every rig held, in a network whose shape the images fix: --fixed-calibration's adjustment (one similarity
        # scale). Where they leave it open (rigs not tied to the rest through three-rig points) the measurements
        # must shape it inside the adjustment, which the refined path does with the calibration held.
        if held and all(d.held for d in decisions) and not loosely_tied_rigs(result.reconstruction):
            result = _adjust_fixed(mapped, rigs, scale_spec, options)
            result.warnings = list(dict.fromkeys(warnings + result.warnings))
            result.priors, result.scale_spec, result.rigs = priors, scale_spec, tuple(rigs)
            try:  # the images' noise, as the refined result reports it (and the covariance would estimate it)
                result.pixel_sigma = estimate_pixel_sigma(result.reconstruction, options.max_reprojection_error_px)
            except ReconstructionError:
                pass
            result.options = replace(options, calibration=Calibration.FIXED)  # the sampled band's draws: held too
            result.decisions = decisions
            return result
        if held:  # from the first pass's network: a shape the measurements had to pull far is not pulled again
            result = _refine(result.reconstruction, rigs, scale_spec, options, priors, held)
            result.decisions = decisions
            result.warnings = list(dict.fromkeys(warnings + result.warnings))
    if result.scale_source != ScaleSource.NONE and with_covariance:
        if result.covariance is None:
            result.covariance = joint_covariance(result)
        result.scale_relative_sigma = network_size_sigma(result.covariance, result.reconstruction)
        if result.scale is not None and result.scale_relative_sigma is not None:
            result.scale = ScaleEstimate(1.0, result.scale_relative_sigma, result.scale.measurements,
                                         result.scale.unused)
    return result


def _refine(mapped: pycolmap.Reconstruction, rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None,
            options: AdjustOptions, priors: CalibrationPriors, held: frozenset[str]) -> AdjustResult:
    """The refined adjustment (without its covariance), the ``held`` rigs' calibration at rigs.yaml's values."""
    rec = pycolmap.Reconstruction(mapped)
    if rec.num_reg_frames() < 2:
        raise ReconstructionError("fewer than two rigs were registered; nothing to calibrate")
    source, gauge = _choose_gauge(rec, scale_spec)
    if source == ScaleSource.MEASUREMENTS:  # a metric first guess: scale the world, then restore E^sl
        first = estimate_scale(rec, scale_spec)  # type: ignore[arg-type]  # MEASUREMENTS come from a scale spec
        rec.transform(pycolmap.Sim3d(first.metres_per_unit, pycolmap.Rotation3d(), np.zeros(3)))
    restore_calibration(rec, rigs)
    try:
        pixel_sigma = estimate_pixel_sigma(rec, options.max_reprojection_error_px)
    except ReconstructionError:  # a start far from the solution: most observations are beyond the threshold
        pixel_sigma = options.loss_scale_px
    problem, rounds, warnings = None, 0, []
    for rounds in range(1, options.max_rounds + 1):
        # Round 1 with the squared loss: when the measurements reshape a network whose images leave its shape open
        # (a 4-rig circle), a robust loss lets the images give up instead of following.
        robust = rounds > 1 or options.max_rounds == 1  # a single round (from an adjusted model): robust
        problem = JointProblem(rec, rigs, priors, scale_spec, options, pixel_sigma, gauge=gauge, robust=robust,
                               held_rigs=held)
        problem.stop_as(final=options.max_rounds == 1)
        summary = problem.solve_to_convergence()  # a long reshape: go on until Ceres converges, then judge outliers
        logger.debug("Adjustment round %d: %s", rounds, summary.BriefReport())
        if options.max_rounds == 1:  # one solve from an adjusted model (the sampled band's draws use its cameras
            break  # and poses): no outliers to judge, and pixel_sigma stays the one that weighted it
        trial = pycolmap.Reconstruction(rec)  # this round's problem refers to rec's blocks: filter a copy first
        filter_outliers(trial, options.max_reprojection_error_px)
        emptied = frames_without_points(trial)
        if emptied:  # the images no longer agree with the priors and measurements: keep them, stop filtering
            inconsistent = (f"ADJUSTMENT INCONSISTENT: after adjustment round {rounds}, every observation of "
                            f"{', '.join(emptied)} lies beyond {options.max_reprojection_error_px:g} px (or on too "
                            "narrow an angle): the matches, rigs.yaml and scale.yaml disagree and the poses are "
                            "unreliable; check the scale measurements and the weakest image pairs")
            logger.warning(inconsistent)
            warnings.append(inconsistent)
            break
        observations = rec.compute_num_observations()
        removed = filter_outliers(rec, options.max_reprojection_error_px)
        try:
            new_sigma = estimate_pixel_sigma(rec, options.max_reprojection_error_px)
        except ReconstructionError:  # fewer observations than unknowns (two rigs, a dozen matches): keep the last
            logger.warning("Too few observations to re-estimate the pixel noise: %.3f px kept", pixel_sigma)
            new_sigma = pixel_sigma
        logger.info("Adjustment round %d: %d observations dropped, pixel noise %.3f -> %.3f px", rounds, removed,
                    pixel_sigma, new_sigma)
        settled = abs(new_sigma / pixel_sigma - 1.0) < 0.05
        pixel_sigma = new_sigma
        if removed <= NEGLIGIBLE_DROP * observations and settled and rounds > 1:  # the last round is a robust one
            break
    if options.max_rounds > 1:
        # The rounds stop at a looser tolerance (Levenberg-Marquardt creeps near the minimum: 32 rigs, 55 and 40
        # iterations of 0.35 s for a relative cost change of 3e-6); the result is this last solve's, which goes on
        # until less than FINAL_SETTLE_CHI2 is left to gain (SettledStop). A new problem: the last round's refers
        # to the observations and points filter_outliers may have deleted.
        problem = JointProblem(rec, rigs, priors, scale_spec, options, pixel_sigma, gauge=gauge, robust=True,
                               held_rigs=held)
        problem.stop_as(final=True)
        problem.solve_to_convergence()
    scale = problem.scale_estimate()  # type: ignore[union-attr]  # the loop sets problem
    for row in problem.unused:  # type: ignore[union-attr]
        logger.warning("Scale measurement left out: %s", row)
    result = AdjustResult(rec, source, scale, _metres_per_mapping_unit(mapped, rec),
                          float(rec.compute_mean_reprojection_error()), calibration=Calibration.REFINE, gauge=gauge,
                          rigs=tuple(rigs), priors=priors, scale_spec=scale_spec, options=options, pixel_sigma=pixel_sigma,
                          rounds=rounds, warnings=warnings, held_rigs=held)
    return result
