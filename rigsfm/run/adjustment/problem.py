"""The refined adjustment's Ceres problem (``JointProblem``): COLMAP's bundle adjuster with calibration priors and
the scale measurements as residuals, and when its solve stops."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import pyceres
import pycolmap
import pycolmap.cost_functions  # not imported by ``import pycolmap``
import scipy.sparse as sp

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.geometry import skew
from rigsfm.core.names import name_of
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.costs import CameraDistanceCost, CentreTerm, LengthCost
from rigsfm.run.adjustment.model import (
    images_of_camera,
    sensor_from_rig_view,
)
from rigsfm.run.adjustment.priors import CalibrationPriors, pose_prior_residual_covariance
from rigsfm.run.adjustment.result import Gauge
from rigsfm.run.adjustment.scale import (
    Measurement,
    ScaleEstimate,
    UnusableMeasurement,
    triangulate_in_images,
)
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.options import AdjustOptions

MAX_SOLVES_PER_ROUND = 5
ROUND_FUNCTION_TOLERANCE = 1e-6  # the rounds (outliers, pixel noise)
FINAL_FUNCTION_TOLERANCE = 1e-9  # the result
FINAL_SETTLE_CHI2 = 0.04  # the result: stop with less than this chi^2 left to gain (0.2 sigma; SettledStop)
SETTLE_STEPS = 20  # a creeping solve's remaining steps gain at most ~20 times its last (SettledStop)


@dataclass
class _Measurement:
    kind: str
    label: str
    meters: float
    sigma: float  # of the measurement, plus what constant (unobserved) E^sl adds to it (metres)
    length: Callable[..., float]  # () -> metres in the current model


def jacobian_csr(jacobian: pyceres.CRSMatrix) -> sp.csr_matrix:
    """A Ceres Jacobian (``Problem.evaluate_jacobian``) as scipy's CSR matrix."""
    return sp.csr_matrix((np.asarray(jacobian.values), np.asarray(jacobian.cols), np.asarray(jacobian.rows)),
                         shape=(jacobian.num_rows, jacobian.num_cols))


class JointProblem:
    """COLMAP's bundle adjuster over ``reconstruction`` (changed in place by :meth:`solve`) with intrinsics and
    observed E^sl refined, plus priors (unless ``with_priors`` is False: then the calibration is in the problem,
    for its Jacobian, but only sigma-0 parameters are held) and measurements. Keeps the Python cost functions
    and the known lengths' end points alive as long as the problem."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, rigs: Sequence[RigCalibration],
                 priors: CalibrationPriors, scale_spec: ScaleSpec | None, options: AdjustOptions,
                 pixel_sigma: float, *, gauge: Gauge, robust: bool, with_priors: bool = True,
                 held_rigs: frozenset[str] = frozenset(), consider_held: bool = False,
                 point_sigmas: Mapping[int, float] | None = None):
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
        # point3D_id -> its observations' own noise (px per coordinate), in place of the pooled one (heads)
        self.point_sigmas = dict(point_sigmas or {})
        # image_id -> the residual blocks of its observations of those points (the heads' shared error per view:
        # rigsfm.run.adjustment.heads_error)
        self.point_sigma_blocks: dict[int, list] = {}
        self._weigh_points()
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

    def _weigh_points(self) -> None:
        """The observations of ``point_sigmas``' points weighed at their own noise: COLMAP's residuals of such a
        point are removed with its block (Ceres removes a parameter block's residuals with it) and added again as
        COLMAP's cost functions with 2D detection noise, ``(sigma / weight_sigma)^2`` (the problem's residuals are
        in pixels at the images' weighting noise), under the same loss. A point's residuals then weigh
        ``(weight_sigma / sigma)^2`` of a keypoint's, and the robust loss meets them at as many sigmas."""
        rec = self.reconstruction
        loss = self.ba_options.ceres.create_loss_function()
        self._keep.append(loss)
        for point_id in sorted(self.point_sigmas):
            if not rec.exists_point3D(point_id):  # dropped as an outlier since
                continue
            point = rec.points3D[point_id]
            if not self.problem.has_parameter_block(point.xyz):
                continue
            self.problem.remove_parameter_block(point.xyz)
            point_cov = (float(self.point_sigmas[point_id]) / self.weight_sigma) ** 2 * np.eye(2)
            for element in point.track.elements:
                image = rec.image(element.image_id)
                camera = rec.cameras[image.camera_id]
                frame = rec.frame(image.frame_id)
                xy = np.asarray(image.points2D[element.point2D_idx].xy, dtype=np.float64)
                # registered frames have their poses
                rig_block = frame.rig_from_world.params  # type: ignore[union-attr]
                if image.is_ref_in_frame():
                    cost = pycolmap.cost_functions.ReprojErrorCost(camera.model, point_cov, xy)
                    blocks = [point.xyz, rig_block, camera.params]
                else:
                    sensor = sensor_from_rig_view(rec, frame.rig_id, camera.sensor_id)
                    if self.problem.has_parameter_block(sensor.params):
                        cost = pycolmap.cost_functions.RigReprojErrorCost(camera.model, point_cov, xy)
                        blocks = [point.xyz, sensor.params, rig_block, camera.params]
                    else:
                        cost = pycolmap.cost_functions.RigReprojErrorCost(camera.model, point_cov, xy,
                                                                          pycolmap.Rigid3d(sensor))  # type: ignore[call-overload]
                        blocks = [point.xyz, rig_block, camera.params]
                block = self.problem.add_residual_block(cost, loss, blocks)
                self.point_sigma_blocks.setdefault(int(element.image_id), []).append(
                    (block, float(self.point_sigmas[point_id]), xy))
                self._keep.append(cost)

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
    Levenberg-Marquardt creeps near the minimum (each step gaining nearly as much as the last, where the squared
    loss converges in a few): the steps still to come then gain at most ~``SETTLE_STEPS`` times the last one. The cost is ``weight_sigma**2 / 2`` times the chi^2 of the whitened residuals, and the chi^2 left to
    gain bounds every derived quantity's distance to the optimum: at most ``sqrt(chi2)`` of its reported sigma."""

    def __init__(self, cost: float):
        super().__init__()
        self.cost = float(cost)

    def __call__(self, summary: pyceres.IterationSummary) -> pyceres.CallbackReturnType:
        if summary.iteration > 0 and summary.step_is_successful and 0.0 <= summary.cost_change < self.cost:
            return pyceres.CallbackReturnType.SOLVER_TERMINATE_SUCCESSFULLY
        return pyceres.CallbackReturnType.SOLVER_CONTINUE
