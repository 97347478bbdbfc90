"""Stage 6, adjust: the metric bundle adjustment with the rigs' calibration, two ways (``AdjustOptions.calibration``).

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

Then the refinement is tested (:func:`hold_or_refine`: the images must inform some direction of the network's
calibration more than rigs.yaml's sigmas do, and the network's change must be consistent with the information they
give about it, else every rig is held); a rig they barely observe is held at rigs.yaml's values and the network
adjusted again; with every rig held, and the network's shape fixed by the images, the adjustment is ``FIXED``'s.
Where the test refines every rig, the tracks that alone pull the refined calibration by more than
``MAX_TRACK_INFLUENCE`` (Cook's distance, ``rigsfm.run.adjustment.influence``: on a crowd, matches across walking
bodies that fit after adjustment) are removed, the network adjusted again at the first pass's pixel noise and tested
again, until no track is above it or the test holds a rig: the rule may hold what the test refined, never refine what
it held (not with narrow observations, the mapping model's or the narrow second pass's: there a narrow track's pull
on E^sl is its purpose).
On a weak network (two rigs registered from a few dozen clicks) the images cannot inform the calibration, and
refining it anyway moved the narrow cameras further from the truth than holding it; a network of two rigs is held
however well the images inform it (``decisions.MIN_RIGS_TO_REFINE``: the tests cannot tell its losing refinements
from its winning ones).

A parameter no image observes (intrinsics and E^sl of a narrow camera without points) is not in COLMAP's problem:
it stays at rigs.yaml's value, and its prior enters the covariance as an independent block. Residuals are whitened
and in pixels: priors and measurements are multiplied by the images' weighting noise (the estimated reprojection
noise times ``pixel_sigma_inflation``). Gauge: one frame held when the scale is observed (measurements, or metric
E^sl baselines with narrow observations), else COLMAP's TWO_CAMS_FROM_WORLD (which also holds the scale).
Solved with ``pyceres.solve``: ``CeresBundleAdjuster.solve`` holds the GIL, and a Ceres worker thread that
evaluates one of the Python measurement costs would wait for it forever.

``FIXED`` (``--fixed-calibration``): hold every E^sl and intrinsic exactly, bring
the network to metric scale with one similarity scale fitted to the measurements, re-run bundle adjustment.

The scale trap (both): without observations in the narrow images, the mapped world has arbitrary units while E^sl
is metric, and ``Reconstruction.transform(Sim3d)`` scales every ``sensor_from_rig`` too. So: scale the world to
metric first, then restore E^sl (and the calibrated intrinsics) from rigs.yaml, then adjust. Narrow poses then
follow as ``narrow_from_wide * wide_from_world``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Collection, Sequence
from dataclasses import replace

import numpy as np
import pycolmap

from rigsfm.core.errors import ReconstructionError
from rigsfm.core.residuals import reprojection_errors
from rigsfm.core.rig import RigCalibration
from rigsfm.run.adjustment.covariance import joint_covariance, network_size_sigma
from rigsfm.run.adjustment.decisions import contradiction, hold_or_refine
from rigsfm.run.adjustment.influence import track_influence
from rigsfm.run.adjustment.model import (
    constrained_bundle_adjustment,
    estimate_pixel_sigma,
    filter_outliers,
    frames_without_points,
    has_narrow_observations,
    restore_calibration,
)
from rigsfm.run.adjustment.priors import CalibrationPriors, calibration_priors
from rigsfm.run.adjustment.problem import JointProblem
from rigsfm.run.adjustment.result import AdjustResult, Gauge, InfluentialTracks, ScaleSource
from rigsfm.run.adjustment.scale import (
    ScaleEstimate,
    estimate_scale,
)
from rigsfm.run.adjustment.track_baseline import delete_points_without_baseline
from rigsfm.run.inputs.scale_file import ScaleSpec
from rigsfm.run.mapping.ties import loosely_tied_rigs
from rigsfm.run.options import AdjustOptions, Calibration

logger = logging.getLogger(__name__)


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


def adjust(
    mapped: pycolmap.Reconstruction,
    rigs: Sequence[RigCalibration],
    scale_spec: ScaleSpec | None,
    options: AdjustOptions | None = None,
    priors: CalibrationPriors | None = None,
    *,
    with_covariance: bool = True,
    held_rigs: Collection[str] | None = None,
    point_sigmas: dict[int, float] | None = None,
) -> AdjustResult:
    """A metric reconstruction (a new object; ``mapped`` is not modified), its calibration refined with
    ``priors`` (default: ``calibration_priors(rigs)``, a good board's) or held (``options.calibration``).
    ``with_covariance``: a refined metric result carries its joint covariance (and the scale's sigma from it).
    ``held_rigs``: refining, hold these rigs' calibration instead of testing each rig's (:func:`hold_or_refine`).
    ``point_sigmas``: refining, point3D_id -> the noise of its observations (px per coordinate) where it is not the
    images' pooled one (heads: :class:`JointProblem`); ``FIXED`` weighs every observation alike."""
    options = options or AdjustOptions()
    start = time.perf_counter()
    if options.calibration == Calibration.REFINE:
        result = _adjust_refined(mapped, rigs, scale_spec, options, priors or calibration_priors(rigs),
                                 with_covariance, held_rigs, point_sigmas or {})
    else:
        result = _adjust_fixed(mapped, rigs, scale_spec, options)
        result.priors, result.scale_spec, result.options = priors, scale_spec, options
    result.rigs = tuple(rigs)
    result.seconds = time.perf_counter() - start
    if result.scale_source == ScaleSource.NONE and held_rigs is None:  # not once per sampled band's draw (40)
        logger.warning("No scale file and no narrow observations: the result is NOT metric")
    return result


def _adjust_fixed(mapped: pycolmap.Reconstruction, rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None,
                  options: AdjustOptions) -> AdjustResult:
    """``FIXED``: E^sl and intrinsics exactly as calibrated."""
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


def _choose_gauge(reconstruction: pycolmap.Reconstruction, scale_spec: ScaleSpec | None) -> tuple[ScaleSource, Gauge]:
    if scale_spec is not None and (scale_spec.camera_distances or scale_spec.known_lengths):
        return ScaleSource.MEASUREMENTS, Gauge.RIGID
    if has_narrow_observations(reconstruction):
        return ScaleSource.NARROW_BASELINES, Gauge.RIGID
    return ScaleSource.NONE, Gauge.TWO_CAMS_FROM_WORLD


def _metres_per_mapping_unit(mapped: pycolmap.Reconstruction, adjusted: pycolmap.Reconstruction) -> float | None:
    """Ratio of the registered frames' spread after and before (RMS distance of the wide centres to their mean)."""
    def spread(rec: pycolmap.Reconstruction) -> np.ndarray:
        # registered frames have their poses
        return np.array([rec.frame(f).rig_from_world.inverse().translation for f in sorted(adjusted.reg_frame_ids())])  # type: ignore[union-attr]

    before, after = spread(mapped), spread(adjusted)
    size = float(np.sqrt(np.mean(np.sum((before - before.mean(axis=0)) ** 2, axis=1))))
    return None if size <= 0 else float(np.sqrt(np.mean(np.sum((after - after.mean(axis=0)) ** 2, axis=1)))) / size


# A robust round that drops at most this share of the observations, with the pixel noise settled, is the last
# (the final solve goes on without them): later rounds drop almost nothing and cost a solve each.
NEGLIGIBLE_DROP = 1e-3


def _adjust_refined(mapped: pycolmap.Reconstruction, rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None,
                    options: AdjustOptions, priors: CalibrationPriors, with_covariance: bool = True,
                    held_rigs: Collection[str] | None = None, point_sigmas: dict[int, float] | None = None
                    ) -> AdjustResult:
    """Every rig's calibration refined, then each rig's refinement tested (:func:`hold_or_refine`); the rigs whose
    refinement fails are held at rigs.yaml's values and the network adjusted again (every rig held in a network whose
    shape the images fix: the result is ``--fixed-calibration``'s, its ``calibration`` FIXED, every track in). Where
    the test refines every rig, the tracks that pull the refined calibration go first, round by round, each round
    tested again (:func:`_without_influential_tracks`). ``held_rigs`` given: those held, no test and no tracks removed
    (the sampled band's draws repeat the estimate's choice)."""
    result = _refine(mapped, rigs, scale_spec, options, priors, frozenset(held_rigs or ()), point_sigmas or {})
    if held_rigs is None and result.scale_source != ScaleSource.NONE:
        result.covariance = joint_covariance(result)
        result.decisions = hold_or_refine(result, result.covariance)
        held_noise, influential = None, None
        # Only where the test refines every rig, and again after each removal: the rule may hold what the test
        # refined, never refine what it held (a refinement that passes only once the tracks that pull it are gone).
        # With narrow observations, a narrow track's pull on E^sl is what it is there for.
        if not any(d.held for d in result.decisions) and not has_narrow_observations(mapped):
            result, influential = _without_influential_tracks(mapped, result, rigs, scale_spec, options, priors)
            held_noise = result.pixel_sigma if influential.removed else None
            result.influential = influential
        held = frozenset(d.rig for d in result.decisions if d.held)
        for decision in result.decisions:
            logger.info("Calibration of %s %s: %s", decision.rig, "held at rigs.yaml" if decision.held else "refined",
                        decision.reason)
        decisions, warnings = result.decisions, result.warnings  # the refined pass's warnings stay true of the input
        contradicted = contradiction(decisions)
        if contradicted:
            logger.warning(contradicted)
            warnings.append(contradicted)
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
            result.decisions, result.influential = decisions, influential
            return result
        if held:  # from the first pass's network: a shape the measurements had to pull far is not pulled again
            result = _refine(result.reconstruction, rigs, scale_spec, options, priors, held, point_sigmas or {},
                             held_noise)
            result.decisions, result.influential = decisions, influential
            result.warnings = list(dict.fromkeys(warnings + result.warnings))
    if result.scale_source != ScaleSource.NONE and with_covariance:
        if result.covariance is None:
            result.covariance = joint_covariance(result)
        result.scale_relative_sigma = network_size_sigma(result.covariance, result.reconstruction)
        if result.scale is not None and result.scale_relative_sigma is not None:
            result.scale = ScaleEstimate(1.0, result.scale_relative_sigma, result.scale.measurements,
                                         result.scale.unused)
    return result


# A track whose deletion alone would move the refined calibration by more than this (Cook's distance: the change's
# squared length in the calibration's posterior sigmas, the robust loss's weights in; module influence) is taken out
# before the hold-or-refine test: on a crowd, a match across walking bodies survives as a two-view track that fits
# after adjustment and pulls the intrinsics and E^sl by several sigma, while a static point's pull is a small share
# of one. Chosen on the benchmark networks (benchmarks/README.md, "A track's influence on the refined calibration").
MAX_TRACK_INFLUENCE = 0.5
# At most this many scorings (one fewer removals and adjustments): once the largest pulls are gone the next ones show,
# and each round costs an adjustment.
MAX_INFLUENCE_ROUNDS = 4


def _without_influential_tracks(mapped: pycolmap.Reconstruction, result: AdjustResult,
                                rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None, options: AdjustOptions,
                                priors: CalibrationPriors) -> tuple[AdjustResult, InfluentialTracks]:
    """``result`` (the first refined pass of ``mapped``, its every rig refined by :func:`hold_or_refine`) again without
    the tracks that pulled its calibration (``MAX_TRACK_INFLUENCE``), scored and removed until none is above it (at
    most ``MAX_INFLUENCE_ROUNDS`` scorings) or the test holds a rig, every pass weighted by the first pass's pixel
    noise (the removed tracks' residuals were part of it, and a noise re-estimated without them would move the test by
    itself), each with its covariance and decisions; ``result`` itself when none is above. With what was removed."""
    start = time.perf_counter()
    pruned, per_round, rounds, largest_kept = None, [], 0, 0.0
    for rounds in range(1, MAX_INFLUENCE_ROUNDS + 1):
        scores = track_influence(result)
        pulling = sorted(pid for pid, score in scores.items() if score > MAX_TRACK_INFLUENCE)
        largest_kept = max((score for score in scores.values() if score <= MAX_TRACK_INFLUENCE), default=0.0)
        if not pulling:
            break
        if rounds == MAX_INFLUENCE_ROUNDS:  # the cap: these stay (removing them would take a pass nobody scores)
            logger.warning("Track influence: %d tracks still pull the refined calibration after %d rounds; kept",
                           len(pulling), rounds)
            break
        logger.info("Track influence, round %d: %d tracks above %g (largest %.3g) removed, the network adjusted again "
                    "at the pixel noise %.3f px", rounds, len(pulling), MAX_TRACK_INFLUENCE,
                    max(scores[pid] for pid in pulling), result.pixel_sigma)
        trial = pycolmap.Reconstruction(pruned or mapped)
        for pid in pulling:
            if trial.exists_point3D(pid):
                trial.delete_point3D(pid)
        emptied = frames_without_points(trial)
        if emptied:  # the pulling tracks are all a frame has: they are its pose, kept (hold-or-refine judges)
            logger.warning("Track influence: the %d tracks that pull the refined calibration are every point of %s; "
                           "kept", len(pulling), ", ".join(emptied))
            break
        pruned = trial
        per_round.append(len(pulling))
        result = _refine(pruned, rigs, scale_spec, options, priors, frozenset(), held_noise=result.pixel_sigma)
        result.covariance = joint_covariance(result)
        result.decisions = hold_or_refine(result, result.covariance)
        if any(d.held for d in result.decisions):  # the test holds now: no more rounds
            break
    influential = InfluentialTracks(removed=sum(per_round), rounds=rounds, per_round=tuple(per_round),
                                    largest_kept=largest_kept, threshold=MAX_TRACK_INFLUENCE,
                                    seconds=time.perf_counter() - start)
    logger.info("Track influence: %d tracks removed in %d scorings (largest kept %.3g; %.1f s)", influential.removed,
                rounds, largest_kept, influential.seconds)
    return result, influential


def _refine(mapped: pycolmap.Reconstruction, rigs: Sequence[RigCalibration], scale_spec: ScaleSpec | None,
            options: AdjustOptions, priors: CalibrationPriors, held: frozenset[str],
            point_sigmas: dict[int, float] | None = None, held_noise: float | None = None) -> AdjustResult:
    """The refined adjustment (without its covariance), the ``held`` rigs' calibration at rigs.yaml's values;
    ``point_sigmas``: those points' observations weighed at their own noise (heads); ``held_noise``: the other
    observations weighted by this pixel noise throughout, not estimated from the residuals."""
    rec = pycolmap.Reconstruction(mapped)
    if rec.num_reg_frames() < 2:
        raise ReconstructionError("fewer than two rigs were registered; nothing to calibrate")
    source, gauge = _choose_gauge(rec, scale_spec)
    if source == ScaleSource.MEASUREMENTS:  # a metric first guess: scale the world, then restore E^sl
        first = estimate_scale(rec, scale_spec)  # type: ignore[arg-type]  # MEASUREMENTS come from a scale spec
        rec.transform(pycolmap.Sim3d(first.metres_per_unit, pycolmap.Rotation3d(), np.zeros(3)))
    restore_calibration(rec, rigs)
    delete_points_without_baseline(rec)  # the mapper's, before round 1's squared loss meets them
    try:
        pixel_sigma = held_noise or estimate_pixel_sigma(rec, options.max_reprojection_error_px, point_sigmas or ())
    except ReconstructionError:  # a start far from the solution: most observations are beyond the threshold
        pixel_sigma = options.loss_scale_px
    problem, rounds, warnings = None, 0, []
    for rounds in range(1, options.max_rounds + 1):
        # Round 1 with the squared loss: when the measurements reshape a network whose images leave its shape open
        # (a 4-rig circle), a robust loss lets the images give up instead of following.
        robust = rounds > 1 or options.max_rounds == 1  # a single round (from an adjusted model): robust
        problem = JointProblem(rec, rigs, priors, scale_spec, options, pixel_sigma, gauge=gauge, robust=robust,
                               held_rigs=held, point_sigmas=point_sigmas)
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
            new_sigma = held_noise or estimate_pixel_sigma(rec, options.max_reprojection_error_px, point_sigmas or ())
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
        # The rounds stop at a looser tolerance (Levenberg-Marquardt creeps near the minimum, many slow steps for a
        # tiny cost change); the result is this last solve's, which goes on
        # until less than FINAL_SETTLE_CHI2 is left to gain (SettledStop). A new problem: the last round's refers
        # to the observations and points filter_outliers may have deleted.
        problem = JointProblem(rec, rigs, priors, scale_spec, options, pixel_sigma, gauge=gauge, robust=True,
                               held_rigs=held, point_sigmas=point_sigmas)
        problem.stop_as(final=True)
        problem.solve_to_convergence()
    scale = problem.scale_estimate()  # type: ignore[union-attr]  # the loop sets problem
    for row in problem.unused:  # type: ignore[union-attr]
        logger.warning("Scale measurement left out: %s", row)
    # without a scale the spread's ratio is of two arbitrary units, not metres (the fixed calibration's None too)
    metres_per_unit = None if source == ScaleSource.NONE else _metres_per_mapping_unit(mapped, rec)
    result = AdjustResult(rec, source, scale, metres_per_unit,
                          float(rec.compute_mean_reprojection_error()), calibration=Calibration.REFINE, gauge=gauge,
                          rigs=tuple(rigs), priors=priors, scale_spec=scale_spec, options=options, pixel_sigma=pixel_sigma,
                          rounds=rounds, warnings=warnings, held_rigs=held, point_sigmas=dict(point_sigmas or {}))
    return result
