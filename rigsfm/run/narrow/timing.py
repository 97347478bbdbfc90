"""Whether the narrow views' heads were taken together (``rigsfm run``'s narrow stage, where heads are the
observations): ``rigsfm associate``'s check of a recording (:func:`rigsfm.associate.sync.shift_counts` and its
rule, :func:`rigsfm.associate.sync.timings`) on run's own head candidates. A tested frame is associated again with
one rig's candidates taken from its own frame k + s (s in -search..search), the others' unchanged, and the rig's
candidates in confident persons are counted; a rig whose count peaks clearly away from 0 is named off in time, and
the narrow stage keeps its heads out of the adjustment (a late rig's heads lie where its walkers will be, not where
the other views triangulate them).

The views' pose corrections (``correct``): ``confirm`` (the default) first carries each view's correction from one
self-calibrating association of the frame before (:func:`rigsfm.associate.solve.associate_views`; ``carry``,
associate's own way), then counts again, each association correcting its views itself (``self``), the rigs whose
carried count peaks away from 0: a late rig's correction carried from the frame before was fitted to its heads a
frame away, which hides its peak (``carry`` alone named no late rig on run's Hough candidates), while ``self`` for
every rig costs five times the CPU. ``own``: the tested rig's correction not carried (a thinner margin); ``none``:
no correction (the counts go flat). Measured on rendered crowds: benchmarks/README.md, *Frame offsets from run's
own heads*.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.associate.solve import associate_views
from rigsfm.associate.sync import (
    NOT_A_RECORDING,
    SEARCH,
    Correction,
    SyncCheck,
    camera_bands,
    confirmed_counts,
    rig_timings,
    shift_counts,
    tested_frames,
)
from rigsfm.associate.views import View, view_pose_sigmas
from rigsfm.core.names import name_of
from rigsfm.core.opencv_threads import one_opencv_thread
from rigsfm.run.narrow.heads import _association_options, head_candidates, scene_footprint

logger = logging.getLogger(__name__)


def time_heads(floor_model: pycolmap.Reconstruction, image_dir: Path, bands: dict[tuple[str, str], float],
               threads: int = 1, correct: Correction = Correction.CONFIRM, searched: dict[str, np.ndarray] | None = None) -> SyncCheck:
    """Each rig's frame offset from its heads (module docstring). ``floor_model``: the first adjustment in the floor
    frame; ``bands``: (i, j) -> the pair's 95 % band (px); ``threads``: images searched at once; ``correct``: the
    views' pose corrections (module docstring); ``searched``: image -> its head candidates, those searched before
    (and this call's, added)."""
    start = time.perf_counter()
    check = SyncCheck("check")
    by_frame: dict[str, dict[str, pycolmap.Image]] = {}
    for image in floor_model.images.values():
        parsed = name_of(image)
        if image.has_pose and parsed.is_narrow:
            by_frame.setdefault(parsed.frame, {})[parsed.camera] = image
    frames = sorted(by_frame)
    cameras = sorted({c for images in by_frame.values() for c in images})
    search = min(SEARCH, (len(frames) - 1) // 2)
    if len(cameras) < 3 or search < 1:
        check.skipped = NOT_A_RECORDING
        return check
    tested = tested_frames(frames, search, lambda i: all(c in by_frame[frames[j]] for c in cameras
                                                         for j in range(i - search, i + search + 1)))
    if not tested:
        check.skipped = "no frame with every narrow view in the frames around it"
        return check
    check.frames, check.search = [frames[i] for i in tested], search
    needed = sorted({(c, frames[j]) for i in tested for c in cameras for j in range(i - search, i + search + 1)})
    footprint = scene_footprint(floor_model)
    searched = {} if searched is None else searched

    def candidates(key: tuple[str, str]) -> np.ndarray:
        return head_candidates(by_frame[key[1]][key[0]], image_dir, footprint, searched)

    with one_opencv_thread(), ThreadPoolExecutor(max(1, threads)) as pool:
        heads = dict(zip(needed, pool.map(candidates, needed)))
    logger.info("frame offsets from the heads: %d images searched (%.1f s)", len(needed), time.perf_counter() - start)
    by_cameras = camera_bands(bands)
    sigmas = view_pose_sigmas(cameras, {(a, b): band for (a, b), band in by_cameras.items()
                                        if a in cameras and b in cameras})
    options = _association_options()
    if correct == Correction.NONE:
        options = dataclasses.replace(options, self_calibration_rounds=0)
    windows: list = []
    for i in tested:
        templates = {}
        for c in cameras:
            for s in range(-search, search + 1):
                view = View.of(by_frame[frames[i + s]][c], heads[(c, frames[i + s])][:, :2])
                view.sigma_pose_px = sigmas[c]
                templates[(c, s)] = view
        if correct in (Correction.CARRY, Correction.OWN, Correction.CONFIRM):
            before = []
            for c in cameras:
                view = View.of(by_frame[frames[i - 1]][c], heads[(c, frames[i - 1])][:, :2])
                view.sigma_pose_px = sigmas[c]
                before.append(view)
            earlier = associate_views(before, options)
            windows.append((templates, dict(zip(cameras, before)), earlier))
        else:
            windows.append((templates, None, None))
    carried: dict[str, dict[int, int]] = {}
    if correct == Correction.CONFIRM:  # the rigs whose carried count peaks away from 0, counted again correcting themselves
        counts, carried = confirmed_counts(windows, cameras, search, options)
    else:
        counts = shift_counts(windows, cameras, search, options, own_pose=correct == Correction.OWN)
    check.rigs = rig_timings(counts, carried)
    check.seconds = time.perf_counter() - start
    logger.info("frame offsets from the heads: %s over %s (%.1f s)", {r: t.counts for r, t in check.rigs.items()},
                check.frames, check.seconds)
    return check
