"""The narrow-observations stage (``rigsfm run --narrow``; :mod:`rigsfm.run.narrow.observations` says how the
matches are found): the second adjustment with them, the check of the held-out matches, and the terminal's line."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.blas_threads import one_blas_thread
from rigsfm.core.geometry import pixel_line_distances
from rigsfm.core.ground import undistort_pixels
from rigsfm.core.names import name_of
from rigsfm.core.processes import in_child
from rigsfm.run.adjustment.adjust import adjust
from rigsfm.run.checks.guided import KEYPOINT_NOISE_PX
from rigsfm.run.checks.self_check import frames_most_rigs_share, synchronised_frames
from rigsfm.run.checks.sync import frames_by_time
from rigsfm.run.deliver import fundamental_matrix
from rigsfm.run.narrow.heads import HEAD_PIXEL_SIGMA, decide_heads, match_heads
from rigsfm.run.narrow.observations import (
    MIN_HELD_OUT,
    HeldOutCheck,
    NarrowObservations,
    PairMatches,
    _j_from_i,
    add_observations,
    decide,
    find_matches,
)
from rigsfm.run.narrow.timing import time_heads
from rigsfm.run.options import NarrowMode, SelfCheckOptions

logger = logging.getLogger(__name__)


def held_out_check(model: pycolmap.Reconstruction, pairs: list[PairMatches], bands: dict) -> list[HeldOutCheck]:
    """Per pair: the held-out matches' distances (pinhole px of j) from the delivered epipolar lines of ``model``,
    against the pair's band (``bands``: (i, j) -> rigsfm.run.adjustment.bands.PairBand or a float) plus the
    keypoints' own noise (``KEYPOINT_NOISE_PX``: the band is geometric, possibly under a pixel)."""

    checks = []
    for pair in pairs:
        if not pair.in_adjustment:
            continue
        band = bands.get((pair.i, pair.j))
        band_px = getattr(band, "band_px", band)
        band_px = None if band_px is None else float(band_px)
        held = pair.held_out
        check = HeldOutCheck(pair.i, pair.j, band_px, int(held.sum()))
        checks.append(check)
        if check.held_out < MIN_HELD_OUT:
            continue
        image_i, image_j = model.find_image_with_name(pair.i), model.find_image_with_name(pair.j)
        camera_i, camera_j = model.cameras[image_i.camera_id], model.cameras[image_j.camera_id]
        f_ji = fundamental_matrix(_j_from_i(image_i, image_j), camera_i, camera_j)
        ui, uj = undistort_pixels(camera_i, pair.xy_i[held]), undistort_pixels(camera_j, pair.xy_j[held])
        distances = pixel_line_distances(np.c_[ui, np.ones(len(ui))] @ f_ji.T, uj)
        distances = distances[np.isfinite(distances)]
        if len(distances) < MIN_HELD_OUT:
            continue
        check.median_px, check.p95_px = float(np.median(distances)), float(np.percentile(distances, 95))
        if band_px is None or not np.isfinite(band_px):
            check.verdict = "no band"
            continue
        check.within_band = float(np.mean(distances <= band_px + KEYPOINT_NOISE_PX))  # as the verdict: noisy matches
        check.verdict = "failed" if check.p95_px > band_px + KEYPOINT_NOISE_PX else "ok"
    return checks


NOT_METRIC = ("the result is not metric, so the narrow images are not matched: each narrow camera's pose follows from "
              "its wide camera's through rigs.yaml's E^sl alone (its offset's metres taken as the mapper's units); give "
              "a scale.yaml")


def narrow_observations(result, world, image_dir: Path, asked: NarrowMode, options: SelfCheckOptions | None = None,
                        offsets: dict[str, int] | None = None, bands: dict | None = None, threads: int = 1,
                        progress: Callable[[int, int], None] | None = None
                        ) -> tuple[pycolmap.Reconstruction | None, NarrowObservations]:
    """Match (in the floor frame; without a floor, along the whole epipolar lines), decide, and return the adjusted
    model with the narrow observations added (None when they are not used) with the record. ``result``: the first
    AdjustResult; ``world``: its WorldResult; ``bands``: the first adjustment's (i, j) -> PairBand or px, which the
    heads' association searches (rigsfm.run.narrow.heads: where the floor matching finds no texture); ``threads``:
    the heads' images searched at once; ``progress(done, total)``: the heads' (match_heads)."""
    start = time.perf_counter()
    if asked == NarrowMode.OFF:
        return None, NarrowObservations(str(asked), False, "not asked (--narrow off)")
    if not world.metric:
        return None, NarrowObservations(str(asked), False, NOT_METRIC)
    floor_model = pycolmap.Reconstruction(result.reconstruction)
    floor_frame = world.frame == "floor"
    if floor_frame:
        world.apply(floor_model)
    features: dict = {}
    pairs = find_matches(floor_model, image_dir, options, floor_frame=floor_frame, offsets=offsets, features=features)
    used, reason = decide(asked, pairs)
    if not floor_frame and not any(p.textured for p in pairs):  # a crowd's heads need heights above the floor
        why = "--world mapping left out" if world.asked == "mapping" else "this run did not find (NO FLOOR FOUND)"
        reason += f"; heads (a crowd of 3D persons) are searched only in the floor frame, which {why}"
    record = NarrowObservations(str(asked), used, reason, pairs, features=features)
    if floor_frame and not any(p.textured for p in pairs):
        # No texture through the floor warp: heads, off the floor, are the features of a crowd of 3D persons.
        heads = heads_instead(floor_model, image_dir, options, offsets, bands, record, threads, progress)
        if heads:
            pairs, used = record.pairs, record.used
    model: pycolmap.Reconstruction | None = None
    if used:
        # The floor frame is a rigid motion of the adjusted model's: pixels and tracks carry over unchanged.
        chosen = pairs if asked == NarrowMode.ON or record.matched_by == "heads" else [p for p in pairs if p.textured]
        for p in chosen:
            p.in_adjustment = True
        model, record.points_added, record.observations_added = add_observations(result.reconstruction, chosen)
        record.held_out = int(sum(p.held_out.sum() for p in chosen))
        if record.matched_by == "heads" and record.head_sigma_px is not None:  # their own noise (narrow.heads, 6)
            record.point_sigmas = {point_id: record.head_sigma_px for point_id in model.points3D
                                   if not result.reconstruction.exists_point3D(point_id)}
        if record.points_added == 0:
            record.used, record.reason, record.held_out = False, reason + "; no match triangulates", 0
            model = None
            for p in chosen:
                p.in_adjustment = False
    record.seconds = time.perf_counter() - start
    logger.info(record.line())
    return model, record


def heads_instead(floor_model: pycolmap.Reconstruction, image_dir: Path, options: SelfCheckOptions | None,
                  offsets: dict[str, int] | None, bands: dict | None, record: NarrowObservations, threads: int = 1,
                  progress: Callable[[int, int], None] | None = None) -> bool:
    """Match heads (rigsfm.run.narrow.heads); where they decide on (``auto``: enough confident persons; ``on``:
    any), ``record`` takes their pairs and decision. Returns whether it did. Without given ``offsets`` a recording's
    rigs are timed by their heads (rigsfm.run.narrow.timing): a rig named off in time is left out of the heads."""
    opt = options or SelfCheckOptions()
    asked_on = record.asked == str(NarrowMode.ON)
    offsets = {r: int(o) for r, o in (offsets or {}).items() if o}
    frames = frames_by_time(floor_model, offsets) if offsets else synchronised_frames(floor_model)
    frames = {f: frames[f] for f in frames_most_rigs_share(frames, opt.max_frames)}
    floats = {}
    for key, band in (bands or {}).items():
        value = getattr(band, "band_px", band)
        if value is not None:
            floats[key] = floats[(key[1], key[0])] = float(value)
    searched: dict = {}
    heads = match_heads(floor_model, image_dir, frames, floats, opt.max_frames, threads, progress, searched)
    enough, reason = decide_heads(heads)
    if (enough or asked_on) and not offsets:  # given offsets pair the frames by time: nothing to check
        record.head_timing = time_heads(floor_model, image_dir, floats, threads, searched=searched)
        late = record.head_timing.named
        if late:  # a late rig's heads lie where its walkers will be: kept out (the others' matched again without it)
            frames = {f: [im for im in images if name_of(im).rig not in late] for f, images in frames.items()}
            heads = match_heads(floor_model, image_dir, frames, floats, opt.max_frames, threads, None, searched)
            enough, reason = decide_heads(heads)
            reason += f" ({', '.join(sorted(late))} left out: not synchronised)"
    record.head_persons, record.head_candidates = heads.persons, sum(heads.candidates.values())
    if not (enough or (asked_on and heads.persons > 0)):
        record.reason += f"; {reason}"
        return False
    record.pairs, record.used, record.matched_by = heads.pairs, True, "heads"
    record.head_check_pairs = heads.check_pairs
    sigma = heads.sigma_px
    record.head_sigma_px = HEAD_PIXEL_SIGMA if sigma is None else sigma
    logger.info("heads' centres weighed at %.2f px per coordinate (%s)", record.head_sigma_px,
                "the fallback: too few residuals" if sigma is None else
                f"from {heads.persons} persons' residuals")
    record.reason = reason if enough else f"asked (--narrow on); {reason}"
    return True


def second_pass(result, world, inputs, options, offsets: dict[str, int] | None = None, bands: dict | None = None,
                progress: Callable[[int, int], None] | None = None):
    """The pipeline's hook after the world stage: ``(result, record)``, the result adjusted again with the narrow
    observations when they are used, else the one given (unchanged). The world stage's floor is kept: the second
    adjustment starts from the first's model with the same gauge (one frame held), so the floor moves by the
    adjustment's change alone, and fitting it again would cost more than the whole second pass. ``offsets``: the
    --frame-offsets FILE's (narrow frames paired by time); ``progress(done, total)``: the heads' (match_heads)."""
    threads = options.num_threads if options.num_threads > 0 else os.cpu_count() or 1
    with one_blas_thread():  # the association runs on one core: a second BLAS thread only spins
        model, record = narrow_observations(result, world, inputs.image_dir, options.narrow, options.self_check,
                                            offsets, bands, threads, progress)
    if model is None:
        return result, record
    return in_child(adjust_on_one_blas_thread, model, inputs.rigs, inputs.scale, options.adjust, inputs.priors,
                    point_sigmas=record.point_sigmas), record


def adjust_on_one_blas_thread(*args, **kwargs):
    """The second adjustment (:func:`rigsfm.run.adjustment.adjust.adjust`'s arguments) with OpenBLAS on one thread:
    its dense algebra (the covariance, the hold-or-refine test) is too small for a second thread to gain more than its
    spinning costs (benchmarks/README.md, "The narrow stage's BLAS threads")."""
    with one_blas_thread():
        return adjust(*args, **kwargs)
