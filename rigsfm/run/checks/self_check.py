"""Stage 11, self_check: the epipolar self-check on synchronised narrow images: measured epipolar distances next to the predicted band.

Narrow images of different rigs with the same frame name were taken at the same instant, so even a moving crowd
is the same scene in both: real correspondences between them must lie on the epipolar lines of the delivered
``F_ji``, within ``epipolar_band_95_px`` (read from narrow_poses.json) for 95 % of them. The check, per pair of
such images whose footprints overlap (on the floor or at head height) by 5 % of the smaller one, matches them
guided by the band (:mod:`rigsfm.run.checks.guided`) and measures their distances from the epipolar lines. How
closely the measured distances follow those of the true correspondences on rendered crowds: benchmarks/README.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.names import ImageName, name_of, registered_narrow_images
from rigsfm.core.summary import SelfCheckPairSummary, SelfCheckSettings, SelfCheckSummary
from rigsfm.run.checks.guided import (
    KEYPOINT_NOISE_PX,
    MIN_MATCHES,
    TOP_HEIGHT_M,
    WIDE_FACTOR,
    NarrowFeatures,
    NarrowView,
    PairCheck,
    check_pair,
    load_narrow,
    overlapping_pairs,
)
from rigsfm.run.checks.sync import frames_by_time
from rigsfm.run.options import SelfCheckOptions

logger = logging.getLogger(__name__)

CHECKED = ("ok", "failed", "not synchronised")  # the verdicts of a pair that had enough matches to measure
MIN_CHECKED_OTHERS = 3  # checked pairs among the others before a rig without any is pointed out


@dataclass
class SelfCheck:
    pairs: list[PairCheck]
    frames: list[str]
    guided_by: str  # "epipolar band and heights 0-2.2 m" or "epipolar band"
    seconds: float
    skipped: str | None = None  # why nothing was checked
    frame_offsets: dict[str, int] = field(default_factory=dict)  # frames paired by time with these (rigsfm.run.checks.sync)
    sync_warning: str | None = None  # FRAMES NOT SYNCHRONISED (rigsfm.run.checks.sync.SyncEstimate.warning)

    def blame_time(self, unsynchronised: Mapping[str, float], warning: str) -> None:
        """Failed pairs with a rig found off in time get the verdict 'not synchronised' (not the calibration)."""
        for pair in self.pairs:
            if pair.verdict == "failed" and {name_of_str(pair.i), name_of_str(pair.j)} & set(unsynchronised):
                pair.verdict = "not synchronised"
        self.sync_warning = warning

    @property
    def warnings(self) -> list[str]:
        out = [self.sync_warning] if self.sync_warning else []
        failed = [p for p in self.pairs if p.verdict == "failed"]
        if failed:
            # failed pairs have their numbers
            worst = max(failed, key=lambda p: p.p95_px / max(p.band_px, 1e-9))  # type: ignore[operator,type-var]
            out.append(f"EPIPOLAR CHECK FAILED: {len(failed)} of {sum(p.verdict != 'too few matches' for p in self.pairs)} "
                       f"narrow pairs match synchronised images farther from the epipolar lines than the 95 % band "
                       f"(worst {worst.i} -> {worst.j}: 95th percentile {worst.p95_px:.2f} px, band "
                       f"{worst.band_px:.2f} px): the poses moved since the calibration, or rigs.yaml is off")
        return out + self.unchecked_rigs()

    def unchecked_rigs(self) -> list[str]:
        """A warning per rig none of whose pairs could be checked while at least half of the other pairs (three or
        more) were: the others show that the frame held something to match, so that rig's narrow view or pose
        differs from theirs (a pose off by more than its band, a view turned away), and its bands are unverified."""
        rigs_of = [{name_of_str(p.i), name_of_str(p.j)} for p in self.pairs]  # each name parsed once
        out = []
        for rig in sorted(set().union(*rigs_of)):
            own = [p for p, rigs in zip(self.pairs, rigs_of) if rig in rigs]
            others = [p for p, rigs in zip(self.pairs, rigs_of) if rig not in rigs]
            checked = sum(p.verdict in CHECKED for p in others)
            if len(own) >= 2 and all(p.verdict == "too few matches" for p in own) and checked >= max(
                    MIN_CHECKED_OTHERS, len(others) / 2):
                out.append(f"UNCHECKED NARROW VIEW: none of {rig}'s {len(own)} narrow pairs found enough matches to "
                           f"check while {checked} of the other {len(others)} pairs were checked: its narrow pose and "
                           f"its pairs' epipolar bands are unverified; look at its pairs in report.html before "
                           f"relying on them")
        return out

    def summary(self) -> SelfCheckSummary:
        """summary.json's ``epipolar_self_check``."""
        return SelfCheckSummary(
            frames=self.frames, guided_by=self.guided_by, skipped=self.skipped, frame_offsets=dict(self.frame_offsets),
            seconds=round(self.seconds, 3),
            settings=SelfCheckSettings(wide_factor=WIDE_FACTOR, keypoint_noise_px=KEYPOINT_NOISE_PX,
                                       min_matches=MIN_MATCHES, top_height_m=TOP_HEIGHT_M),
            pairs=[SelfCheckPairSummary(**p.to_dict()) for p in self.pairs])


def name_of_str(name: str) -> str:
    """The rig of an image name."""
    return ImageName.parse(name).rig


def synchronised_frames(reconstruction: pycolmap.Reconstruction) -> dict[str, list[pycolmap.Image]]:
    """Frame name -> registered narrow images of that frame, for frames of two or more rigs."""
    frames: dict[str, list[pycolmap.Image]] = {}
    for image in registered_narrow_images(reconstruction):
        frames.setdefault(name_of(image).frame, []).append(image)
    return {f: images for f, images in sorted(frames.items()) if len({name_of(im).rig for im in images}) >= 2}


def frames_most_rigs_share(frames: dict[str, list[pycolmap.Image]], count: int) -> list[str]:
    """The ``count`` (at least one) frames of ``frames`` (label -> narrow images) that the most rigs share, earliest
    first among equals, in their order: the first frame may lack a rig (one a frame later in time, or an image
    missing), whose pairs would then go unchecked, or unused, without a word."""
    ranked = sorted(frames, key=lambda f: -len({name_of(im).rig for im in frames[f]}))[:max(1, count)]
    return [f for f in frames if f in ranked]


def epipolar_self_check(reconstruction: pycolmap.Reconstruction, image_dir: Path, narrow_poses: dict,
                        options: SelfCheckOptions | None = None, offsets: dict[str, int] | None = None,
                        cached: dict[tuple[str, str], tuple[NarrowFeatures, NarrowFeatures]] | None = None) -> SelfCheck:
    """The self-check (module docstring) of the ``options.max_frames`` synchronised frames of most rigs, with the
    ``F_ji`` and ``epipolar_band_95_px`` of ``narrow_poses`` (the narrow_poses.json of this model); with
    ``offsets`` (rig -> frames, rigsfm.run.checks.sync) rig r's k-th frame is paired with the others' (k + offset)-th;
    ``cached``: (i, j) -> the pair's features from an earlier pass (:func:`check_pair`): images whose pairs all
    have them are not read again."""
    opt = options or SelfCheckOptions()
    start = time.perf_counter()
    world = narrow_poses.get("world") or {}
    floor_frame = world.get("frame") == "floor" and bool(narrow_poses.get("metric"))
    guided_by = "epipolar band and heights 0-2.2 m above the floor" if floor_frame else "epipolar band"
    offsets = {r: int(o) for r, o in (offsets or {}).items() if o}
    if offsets:
        frames = frames_by_time(reconstruction, offsets)
    else:
        frames = synchronised_frames(reconstruction)
    if not frames:
        return SelfCheck([], [], guided_by, time.perf_counter() - start,
                         "no frame name shared by narrow images of two or more rigs", offsets)
    chosen = frames_most_rigs_share(frames, opt.max_frames)
    by_pair = {(p["i"], p["j"]): p for p in narrow_poses.get("pairs", [])}
    checks = []
    for frame in chosen:
        images = frames[frame]
        pairs = [p for p in overlapping_pairs(reconstruction, images, floor_frame) if p in by_pair]
        cached = cached or {}
        needed = {n for p in pairs if p not in cached for n in p}
        loaded = {name: load_narrow(reconstruction.find_image_with_name(name), Path(image_dir),
                              opt.warp_height_m if floor_frame else None, opt.sift_size) if name in needed
                  else NarrowView(reconstruction.find_image_with_name(name), np.zeros((0, 0), np.uint8), None)
                  for name in sorted({n for p in pairs for n in p})}
        for name_i, name_j in pairs:
            entry = by_pair[(name_i, name_j)]
            if loaded[name_i] is None or loaded[name_j] is None:
                checks.append(PairCheck(frame, name_i, name_j, entry.get("epipolar_band_95_px")))
                continue
            # pairs of loaded images only
            checks.append(check_pair(loaded[name_i], loaded[name_j], np.asarray(entry["F_ji"]),  # type: ignore[arg-type]
                                     entry.get("epipolar_band_95_px"), floor_frame, cached.get((name_i, name_j))))
            c = checks[-1]
            logger.info("self-check %s -> %s: %d matches, p95 %s px, band %s px: %s", name_i, name_j, c.matches,
                        "-" if c.p95_px is None else f"{c.p95_px:.2f}",
                        "-" if c.band_px is None else f"{c.band_px:.2f}", c.verdict)
    skipped = None if checks else "no pair of synchronised narrow images overlaps"
    return SelfCheck(checks, chosen, guided_by, time.perf_counter() - start, skipped, offsets)
