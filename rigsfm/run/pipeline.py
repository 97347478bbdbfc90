"""``rigsfm run``: validate, database, features, mapping, adjust, deliver — in one workspace (:func:`run`)."""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

import rigsfm
from rigsfm.core import processes as stages
from rigsfm.core.errors import InputError, ReconstructionError
from rigsfm.core.executors import Executor, check_reachable
from rigsfm.core.io import write_json_atomic
from rigsfm.core.names import SENSORS, ImageName
from rigsfm.core.processes import in_child
from rigsfm.core.residuals import reprojection_errors
from rigsfm.core.rig import RigCalibration, load_rigs
from rigsfm.core.summary import (
    BANDS_WITH_NARROW,
    CameraError,
    FrameOffsetsSummary,
    InputsSummary,
    MappingSummary,
    Registration,
    ScaleSummary,
    Summary,
)
from rigsfm.core.workspace import Workspace, colmap_log_to, disk_errors_named
from rigsfm.inspect.report import write_report
from rigsfm.run.adjustment.adjust import AdjustResult, ScaleSource, adjust
from rigsfm.run.adjustment.priors import CalibrationPriors, calibration_priors
from rigsfm.run.adjustment.scale_check import check_scale_agreement, unlevel_known_lengths
from rigsfm.run.adjustment.uncertainty import estimate_uncertainty, uncertainty_summary
from rigsfm.run.checks.diagnostics import check_reconstruction
from rigsfm.run.checks.missed_pairs import pairs_report
from rigsfm.run.deliver import (
    changes_from,
    earlier_outputs_warning,
    narrow_poses,
    write_model,
    write_points_ply,
)
from rigsfm.run.inputs.database import check_database_kept, create_database
from rigsfm.run.inputs.images import (
    ImageEntry,
    check_image_folder,
    rig_folders,
    rigs_missing_frames,
    rigs_without_narrow,
    scan_images,
    with_folder_names,
)
from rigsfm.run.inputs.scale_file import ScaleSpec, load_scale
from rigsfm.run.mapping.mapper import MappingResult, run_mapping
from rigsfm.run.matching.extract import extract_features, resolved_first_octave
from rigsfm.run.matching.manual_matches import read_manual_matches, validate_manual_matches
from rigsfm.run.matching.manual_merge import (
    add_manual_matches,
    drop_earlier_manual_matches,
    manual_matches_summary,
)
from rigsfm.run.matching.match import match_features
from rigsfm.run.matching.pairs import drop_unsynchronised_pairs, select_pairs
from rigsfm.run.matching.reuse import drop_changed_images, drop_stale_work
from rigsfm.run.narrow.heads import head_self_check
from rigsfm.run.narrow.stage import held_out_check, second_pass
from rigsfm.run.options import NarrowMode, RunOptions
from rigsfm.run.world.frame import ground_maps, locate_world, validate_world_options

if TYPE_CHECKING:
    from rigsfm.run.checks.self_check import SelfCheck

logger = logging.getLogger(__name__)

# progress(stage, done, total); (stage, 0, 0) when a stage starts, before its total is known.
Progress = Callable[[str, int, int], None]

NO_COVARIANCE = ("NO BANDS: the joint covariance of rig poses and calibration could not be computed (the log's "
                 "'No joint covariance' line says why): narrow_poses.json holds no epipolar bands and no pose sigmas, and "
                 "every rig's calibration stays at rigs.yaml's; the poses are usable, but search correspondences without a "
                 "band (or with the self-check's measured spread) and report the run with its colmap.log and database.db")
# The heavy stages run in a child process (rigsfm.core.processes: Ctrl-C and SIGTERM stop them at once). scipy.stats
# too: every adjustment's hold-or-refine test needs it, imported there lazily to keep the command line's start fast.
STAGE_MODULES = ("rigsfm.run.matching.extract", "rigsfm.run.matching.pairs", "rigsfm.run.matching.match",
                 "rigsfm.run.mapping.mapper", "rigsfm.run.adjustment.adjust", "rigsfm.run.adjustment.uncertainty",
                 "scipy.stats")


@dataclass(frozen=True)
class Inputs:
    image_dir: Path
    rigs: list[RigCalibration]
    images: list[ImageEntry]
    scale: ScaleSpec | None
    priors: CalibrationPriors | None = None  # the calibration's uncertainty (rigs.yaml's sigmas or defaults)
    without_narrow: tuple[str, ...] = ()  # rigsfm.run.inputs.images.rigs_without_narrow: one line per rig
    missing_frames: str | None = None  # rigsfm.run.inputs.images.rigs_missing_frames: one line


@dataclass
class RunResult:
    workspace: Workspace
    reconstruction: pycolmap.Reconstruction
    summary: Summary
    self_check: SelfCheck | None = None  # every checked pair with its distances (summary.json keeps statistics)


def check_out_outside_images(out: Path, image_dir: Path) -> None:
    """Refuse an output folder inside the image folder (or the image folder itself): its sub-folders would be
    taken for rigs by every later run on that image folder."""
    try:
        out_real, images_real = out.resolve(), image_dir.resolve()
    except (OSError, RuntimeError):  # a link loop: the image folder's own check names it
        return
    if out_real == images_real or images_real in out_real.parents:
        where = "is" if out_real == images_real else "lies inside"
        raise InputError(f"--out {out} {where} the image folder {image_dir}, whose every folder must be a rig; "
                         "choose an output folder outside it")


def refuse_a_lone_rig(image_dir: Path, rigs: list[RigCalibration]) -> None:
    """Refuse a network of one rig: every deliverable (a pair's E, F and band, the scale, the floor) joins two rigs'
    views, and one rig's frames, taken from one place, give the mapper no baseline (a rig's board images, run by
    mistake, end in warnings only)."""
    if len(rigs) >= 2 or len(rig_folders(image_dir)) >= 2:  # a folder without its rig is named by scan_images
        return
    names = ", ".join(f"'{rig.name}'" for rig in rigs)
    raise InputError(f"{image_dir}: one rig ({names}); rigsfm calibrates a network of two or more rigs whose wide "
                     "views overlap (each pair's E, F and band joins two rigs): add the other rigs' folders, and "
                     "their calibration to rigs.yaml (a rig's board images are for `rigsfm calibrate`)")


def load_inputs(image_dir: Path, rigs_path: Path, scale_path: Path | None = None) -> Inputs:
    """Validate every input before any heavy work; raises ``InputError`` naming file and fix."""
    rigs = with_folder_names(check_image_folder(image_dir), load_rigs(rigs_path))
    refuse_a_lone_rig(image_dir, rigs)  # before the calibration's warnings: they would not be the user's problem
    priors = calibration_priors(rigs, rigs_path)
    images = scan_images(image_dir, rigs)
    without_narrow = tuple(rigs_without_narrow(image_dir, images, rigs))
    for line in without_narrow:
        logger.warning("NO NARROW IMAGES: %s", line)
    missing_frames = rigs_missing_frames(images, rigs)
    if missing_frames is not None:
        logger.warning("MISSING FRAMES: %s", missing_frames)
    scale = load_scale(scale_path, images, rigs) if scale_path is not None else None
    return Inputs(Path(image_dir), rigs, images, scale, priors, without_narrow, missing_frames)


class _Timings(dict):
    """Wall seconds per stage; ``cpu`` holds the CPU seconds per stage (all threads, the stage processes
    included; on a shared machine the wall time varies with the load, the CPU time much less)."""

    def __init__(self) -> None:
        super().__init__()
        self.cpu: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start, cpu_start = time.perf_counter(), stages.stage_cpu_seconds()
        try:
            yield
        except BaseException:
            logger.info("Stage %s stopped after %.1f s", name, time.perf_counter() - start)
            raise
        self[name] = round(time.perf_counter() - start, 3)
        self.cpu[name] = round(stages.stage_cpu_seconds() - cpu_start, 3)
        logger.info("Stage %s took %.1f s (%.1f s CPU)", name, self[name], self.cpu[name])


def reprojection_table(reconstruction: pycolmap.Reconstruction) -> dict[str, CameraError]:
    """Per camera (``<rig>/<sensor>``): observations, mean and RMS reprojection error."""
    per_camera: dict[str, list[np.ndarray]] = {}
    for name, errors in reprojection_errors(reconstruction).items():
        per_camera.setdefault(ImageName.parse(name).camera, []).append(errors)
    table = {}
    for key, camera_errors in sorted(per_camera.items()):
        e = np.concatenate(camera_errors)
        table[key] = CameraError(observations=int(e.size), mean_px=float(e.mean()) if e.size else None,
                                 rms_px=float(np.sqrt(np.mean(e**2))) if e.size else None)
    return table


def registration_counts(reconstruction: pycolmap.Reconstruction,
                        images: list[ImageEntry]) -> tuple[dict[str, Registration], list[str]]:
    registered = {im.name for im in reconstruction.images.values() if im.has_pose}
    counts = {}
    for sensor in SENSORS:
        names = [e.name for e in images if e.sensor == sensor]
        counts[str(sensor)] = Registration(registered=sum(n in registered for n in names), total=len(names))
    return counts, sorted(e.name for e in images if e.name not in registered)


MAX_METRIC_SCALE_SIGMA = 0.01  # relative; a looser scale is reported as not metric


def is_metric(result: AdjustResult) -> bool:
    if result.scale_source == ScaleSource.MEASUREMENTS:
        return True
    sigma = result.scale_relative_sigma
    return result.scale_source == ScaleSource.NARROW_BASELINES and sigma is not None and sigma < MAX_METRIC_SCALE_SIGMA


def build_summary(inputs: Inputs, options: RunOptions, mapping: MappingResult, result: AdjustResult,
                  timings: dict, database: Path | None = None) -> Summary:
    reconstruction = result.reconstruction
    counts, unregistered = registration_counts(reconstruction, inputs.images)
    metric = is_metric(result)
    warnings = []
    if mapping.fallback:
        warnings.append(f"OTHER MAPPER USED: {mapping.fallback}")
    if result.scale_source == ScaleSource.NONE:
        warnings.append("NOT METRIC: no scale.yaml and no observations in narrow images; units are arbitrary")
    elif not metric:
        warnings.append(
            f"NOT METRIC: the narrow images' observations fix the scale only to +-{100 * result.scale_relative_sigma:.3g} %;"  # type: ignore[operator]
            " give a scale.yaml (rangefinder distance or known length)"
        )
    warnings.extend(result.warnings)
    warnings.extend(check_reconstruction(reconstruction, result.scale, database))
    warnings.extend(unlevel_known_lengths(reconstruction, inputs.scale))
    if inputs.priors is not None and inputs.priors.warning():
        warnings.append(inputs.priors.warning())  # type: ignore[arg-type]  # checked just above
    if unregistered:
        warnings.append(f"{len(unregistered)} image(s) not registered: {', '.join(unregistered[:5])}")
    warnings.extend(f"NO NARROW IMAGES: {line}" for line in inputs.without_narrow)
    if inputs.missing_frames is not None:
        warnings.append(f"MISSING FRAMES: {inputs.missing_frames}")
    return Summary(
        rigsfm_version=rigsfm.__version__,
        pycolmap_version=pycolmap.__version__,
        # Absolute: explore, report and export --images read the images from any working folder, not only this one.
        inputs=InputsSummary(images=str(inputs.image_dir.absolute()), num_rigs=len(inputs.rigs),
                             scale_file=str(inputs.scale.path.absolute()) if inputs.scale else None),
        options=json_ready(asdict(options)),
        metric=metric,
        scale=ScaleSummary(
            source=str(result.scale_source), metres_per_mapping_unit=result.metres_per_mapping_unit,
            relative_sigma_percent=None if result.scale_relative_sigma is None else 100.0 * result.scale_relative_sigma,
            measurements=result.scale.residuals() if result.scale else []),
        mapping=MappingSummary(asked=str(options.mapping.mapper), used=str(mapping.mapper), fallback=mapping.fallback,
                               few_matches=bool(options.mapping.few_matches)),
        registered=counts,
        unregistered=unregistered,
        calibration_decisions=[asdict(d) for d in result.decisions],
        influential_tracks=asdict(result.influential) if result.influential is not None else None,
        num_points3D=reconstruction.num_points3D(),
        mean_reprojection_error_px=result.mean_reprojection_error_px,
        reprojection_error=reprojection_table(reconstruction),
        timings_s=dict(timings),
        warnings=warnings,
    )


def json_ready(value):
    """Options as JSON: paths and enums as strings."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    return str(value) if isinstance(value, Path) else value


def run(
    image_dir: Path,
    rigs_path: Path,
    out: Path,
    scale_path: Path | None = None,
    options: RunOptions | None = None,
    progress: Progress | None = None,
) -> RunResult:
    """The whole pipeline; every artifact lands in ``out`` (see :class:`rigsfm.core.workspace.Workspace`)."""
    options = options or RunOptions()
    stages.start(preload=STAGE_MODULES)  # imports them in the stages' forkserver while the inputs are checked
    timings = _Timings()
    workspace = Workspace(Path(out))
    with timings.stage("validate"):
        validate_world_options(options.world)  # the options first: no input warnings before their refusal
        check_out_outside_images(Path(out), Path(image_dir))
        # OUT's refusals before the inputs' warnings (prepare repeats them under the lock)
        workspace.refuse(overwrite=options.overwrite)
        inputs = load_inputs(image_dir, rigs_path, scale_path)
        if options.executor == Executor.RAY and options.address:
            check_reachable(options.address)  # before any work: ray.init would retry an unreachable one for ever
        manual_pairs = {} if options.manual_matches is None else validate_manual_matches(
            options.manual_matches, read_manual_matches(options.manual_matches), inputs.images, inputs.rigs)
        given_offsets = _given_frame_offsets(options, inputs)
        if given_offsets and options.matching.narrow_features:
            options = replace(options, matching=replace(options.matching, frame_offsets=given_offsets))
    lowered = options.mapping.few_matches is None and bool(manual_pairs)
    if options.mapping.few_matches is None:
        options = replace(options, mapping=replace(options.mapping, few_matches=bool(manual_pairs)))
    with workspace.lock(), disk_errors_named(workspace.root):
        workspace.prepare(overwrite=options.overwrite)
        if lowered:  # once OUT is taken: a run refused there printed it before its one red line
            logger.warning("Manual matches given: the mapper's match-count thresholds are lowered for them")
        return _run_locked(workspace, inputs, manual_pairs, options, timings, progress, given_offsets)


def _replaced_poses(workspace: Workspace) -> dict | None:
    """narrow_poses.json of the finished result in OUT (its summary.json written), or None."""
    if not workspace.summary.is_file():
        return None
    try:
        return json.loads(workspace.narrow_poses.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _given_frame_offsets(options: RunOptions, inputs: Inputs) -> dict[str, int] | None:
    """The --frame-offsets FILE, checked against the rigs and the recording (before any heavy work)."""
    given = options.self_check.frame_offsets
    if given is None or str(given) == "auto":
        return None
    from rigsfm.run.checks.sync import read_frame_offsets

    frames: dict[str, int] = {}
    for entry in inputs.images:
        if entry.sensor == "narrow":
            frames[entry.rig] = frames.get(entry.rig, 0) + 1
    return read_frame_offsets(Path(given), [rig.name for rig in inputs.rigs], frames)


def _self_check(poses: dict, inputs: Inputs, reconstruction: pycolmap.Reconstruction, options: RunOptions,
                given_offsets: dict[str, int] | None, cached: dict | None = None
                ) -> tuple[SelfCheck, FrameOffsetsSummary]:
    """The epipolar self-check against ``poses`` (narrow_poses.json's record, as written), its frames paired by time where offsets are given or estimated (``auto``); when
    it fails without offsets and the recording has several frames, the offsets are estimated, and the pairs a
    rig off in time explains are put down to it (rigsfm.run.checks.sync) instead of the calibration."""
    from rigsfm.run.checks.self_check import epipolar_self_check
    from rigsfm.run.checks.sync import estimate_frame_offsets

    opt = options.self_check

    def estimate():
        return estimate_frame_offsets(reconstruction, inputs.image_dir, poses, max_offset=opt.max_offset_frames,
                                      sift_size=opt.sift_size, warp_height_m=opt.warp_height_m)

    asked = None if opt.frame_offsets is None else str(opt.frame_offsets)
    sync = estimate() if asked == "auto" else None
    applied = dict(given_offsets or {}) if sync is None else sync.applicable
    check = epipolar_self_check(reconstruction, inputs.image_dir, poses, opt, applied, cached)
    if asked is None and any(p.verdict == "failed" for p in check.pairs):
        sync = estimate()
        if sync.warning:
            check.blame_time(sync.named, sync.warning)
    elif asked == "auto":
        if applied:
            logger.warning("Frame offsets estimated and applied: %s", applied)
        left = sync.left_after(applied)  # type: ignore[union-attr]
        if left:  # a fraction of a frame: only whole frames can be applied
            check.blame_time(left, sync.fraction_warning(applied))  # type: ignore[union-attr]
    record = FrameOffsetsSummary(asked=asked, applied=applied, estimate=None if sync is None else sync.to_dict())
    return check, record


def _run_locked(workspace: Workspace, inputs: Inputs, manual_pairs: dict, options: RunOptions, timings: _Timings,
                progress: Progress | None, given_offsets: dict[str, int] | None = None) -> RunResult:
    def report(stage: str) -> Callable[[int, int], None] | None:
        """The stage's progress callback; called as the stage starts, so that its clock starts there too (its
        first count may come only at its end)."""
        if not progress:
            return None
        progress(stage, 0, 0)
        return lambda done, total: progress(stage, done, total)

    threads = options.num_threads
    num_wide = sum(e.sensor == "wide" for e in inputs.images)
    with colmap_log_to(workspace.colmap_log):
        with timings.stage("database"):
            create_database(workspace.database, inputs.rigs, inputs.images, overwrite=options.overwrite)
        with timings.stage("features"):
            features_progress = report("features")
            drop_stale_work(workspace.database, workspace.feature_settings, options.matching,
                            resolved_first_octave(workspace.database, inputs.images, options.matching))
            drop_changed_images(workspace.database, workspace.image_contents, inputs.images)
            in_child(extract_features, workspace.database, inputs.image_dir, inputs.images, options.matching,
                     features_progress, num_threads=threads, executor=options.executor,
                     address=options.address, workers=options.workers)
        with timings.stage("matching"):
            matching_progress = report("matching")
            drop_earlier_manual_matches(workspace.database, manual_pairs)
            selection = in_child(select_pairs, workspace.database, inputs.images, options.matching)
            in_child(match_features, workspace.database, inputs.images, options.matching, workspace.pairs,
                     matching_progress, num_threads=threads, selection=selection)
            check_database_kept(workspace.database, inputs.images)
            drop_unsynchronised_pairs(workspace.database, inputs.images, options.matching.frame_offsets)
        manual_reports = []
        if manual_pairs:
            with timings.stage("manual_matches"):
                manual_reports = add_manual_matches(workspace.database, manual_pairs, options.matching.max_error_px)
        with timings.stage("mapping"):
            done = [0]
            if progress:
                progress("mapping", 0, num_wide)

            def on_registered() -> None:
                done[0] += 1
                if progress:
                    progress("mapping", min(done[0], num_wide), num_wide)

            try:
                mapping = in_child(run_mapping, workspace, inputs.image_dir, options.mapping, num_wide=num_wide,
                                   num_threads=threads, on_registered=on_registered)
            except ReconstructionError as error:
                check_database_kept(workspace.database, inputs.images)  # its loss is the cause, not the images
                if not manual_reports:
                    raise
                kept = "; ".join(f"{r.image_a} <-> {r.image_b}: {r.kept} of {r.given} kept" for r in manual_reports)
                raise ReconstructionError(f"{error}. Manual matches: {kept}") from None
            if progress:
                progress("mapping", mapping.reconstruction.num_reg_frames(), num_wide)
            if inputs.scale is not None:  # a measurement in other units would drag the adjustment for minutes
                check_scale_agreement(mapping.reconstruction, inputs.scale, inputs.rigs)
        with timings.stage("adjust"):
            result = in_child(adjust, mapping.reconstruction, inputs.rigs, inputs.scale, options.adjust, inputs.priors)
        metric = is_metric(result)
        with timings.stage("world"):  # the floor, fitted in the adjusted model's frame; moved there after the bands
            world = locate_world(result.reconstruction, inputs.image_dir, inputs.scale,
                                 [rig.name for rig in inputs.rigs], options.world, metric=metric)
        narrow = None
        # Of the adjustment without narrow observations: the heads search its bands (narrow.heads).
        with timings.stage("uncertainty"):
            floor, floor_source = world.analysis_floor(result.reconstruction, result.scale_spec)
            uncertainty = in_child(estimate_uncertainty, result, floor=floor, floor_source=floor_source)
        if options.narrow != NarrowMode.OFF:  # narrow observations: a second adjustment where they are used
            with timings.stage("narrow_observations"):
                first, (result, narrow) = result, second_pass(result, world, inputs, options, given_offsets,
                                                              uncertainty.bands, report("narrow"))
                result.influential = result.influential or first.influential  # the second starts from its model
                metric = is_metric(result)
            if result is not first and narrow.bands_from == BANDS_WITH_NARROW:  # (not with heads: bands_from)
                with timings.stage("uncertainty_final"):
                    # Same gauge as the first (one frame held), world.apply not yet: the floor fit's frame.
                    floor, floor_source = world.analysis_floor(result.reconstruction, result.scale_spec)
                    uncertainty = in_child(estimate_uncertainty, result, floor=floor, floor_source=floor_source)
                    uncertainty.bands_from = BANDS_WITH_NARROW
            if result is not first:  # the second adjustment moved the network: the floor fitted again on it
                with timings.stage("world_refit"):  # after the bands, which keep the first fit's floor
                    world.refit(result.reconstruction, inputs.scale)
        with timings.stage("deliver"):
            world.add_pose_uncertainty(result.reconstruction, uncertainty.covariance)  # before the move: its frame
            world.apply(result.reconstruction)  # a rigid move: the bands and sigmas above are unchanged by it
            world.set_narrow_heights(result.reconstruction, uncertainty.narrow)
            ground = ground_maps(result.reconstruction, world.plane_heights) if world.plane_heights else None
            # an --overwrite run's files replace the old result's from here: without its summary.json the workspace
            # reads as unfinished until this run writes its own, not as the old summary over the new model; nor is the
            # old report.html left to show the replaced result until then
            earlier = _replaced_poses(workspace)  # the finished result this run replaces, to say what changed
            workspace.summary.unlink(missing_ok=True)
            workspace.report.unlink(missing_ok=True)
            write_model(result.reconstruction, workspace.sparse, overwrite=True)
            poses = narrow_poses(result.reconstruction, metric=metric, bands=uncertainty.bands, world=world.to_dict(),
                                 ground=ground)
            replaced = changes_from(earlier, poses)
            write_json_atomic(workspace.narrow_poses, poses, overwrite=True)
            write_points_ply(result.reconstruction, workspace.points_ply, overwrite=True)
        with timings.stage("check_pairs"):
            pairs, pairs_warning = pairs_report(result.reconstruction, selection)
    self_check = frame_offsets = None
    if options.self_check.enabled:
        with timings.stage("self_check"):
            self_check, frame_offsets = _self_check(poses, inputs, result.reconstruction, options, given_offsets,
                                                    None if narrow is None else narrow.features)
    if narrow is not None and narrow.used:
        narrow.held_out_checks = held_out_check(result.reconstruction, narrow.pairs, uncertainty.bands)
        if self_check is not None and narrow.matched_by == "heads":
            narrow.head_verdicts = head_self_check(self_check.pairs, narrow.head_check_pairs, result.reconstruction,
                                                  poses)
    summary = build_summary(inputs, options, mapping, result, timings, workspace.database)
    summary.world = world.summary()
    summary.warnings.extend(world.warnings)
    if self_check is not None:
        summary.epipolar_self_check = self_check.summary()
        summary.warnings.extend(self_check.warnings)
        summary.frame_offsets = frame_offsets
    if narrow is not None:
        summary.narrow_observations = narrow.summary()
        summary.warnings.extend(narrow.warnings)
    summary.pairs = pairs
    summary.cpu_s = dict(timings.cpu)
    if pairs_warning:
        summary.warnings.append(pairs_warning)
    summary.replaced = replaced
    made_before = earlier_outputs_warning(workspace)  # an --overwrite run replaced the model they were made from
    if made_before:
        summary.warnings.append(made_before)
    if options.manual_matches is not None:
        summary.manual_matches = manual_matches_summary(options.manual_matches, manual_reports)
    summary.uncertainty = uncertainty_summary(result, uncertainty, metric=metric)
    if uncertainty.covariance is None:
        summary.warnings.append(NO_COVARIANCE)
    write_json_atomic(workspace.summary, summary.to_json())
    write_report(workspace.root)
    return RunResult(workspace, result.reconstruction, summary, self_check)
