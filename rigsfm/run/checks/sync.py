"""Are the narrow images of one frame name simultaneous? The per-rig frame offset of an unsynchronised recording.

Rigs are static, so their poses, ``F_ji`` and bands hold for every frame; only the moving crowd tells whether
frame ``k`` of two rigs is one instant. A rig whose frame ``k`` was taken at time ``k + o`` (frames) is ``o``
frames off. For each pair of rigs (a, b) whose narrow footprints overlap and each candidate ``d`` in
``-max_offset .. max_offset``, narrow a frame ``k`` is matched with narrow b frame ``k + d`` exactly as the
epipolar self-check matches a pair (:mod:`rigsfm.run.checks.self_check`: j warped into i's view through the floor,
candidates near i's epipolar line and between heights 0 and 2.2 m, ratio test, mutual best), with a fixed lateral
tolerance of ``WIDE_FACTOR`` x band + keypoint noise (at least ``WIDE_FACTOR`` x keypoint noise: a band under a
pixel); the pair's score at ``d`` is the share of the matches within band + keypoint noise of their epipolar lines
(pooled over up to ``frames_per_offset`` frame pairs). Simultaneous images of a moving crowd match on their lines
(share near 1); images a frame apart match walkers that have moved, so the matches spread over the whole tolerance
(share near (band + keypoint noise) / tolerance). a_k and b_{k+d} are simultaneous when ``d = o_a - o_b``.

Per-rig offsets: the integer offsets (``-max_offset .. max_offset``) that maximise the summed scores of the pairs
(each at ``d = o_a - o_b``), every assignment tried for up to ``BRUTE_FORCE_RIGS`` rigs (coordinate ascent beyond),
then shifted so that most rigs are at 0 (ties: the first rig at 0). A rig is named unsynchronised only where the
evidence is clear: one of its pairs is consistent (score >= ``CONSISTENT``) at the rig's offset and not with the
rig at 0 (a pair whose epipolar lines run along the crowd's motion cannot tell, so one pair that can is enough).

Sub-frame offsets: a walker crosses several pixels of a long-focal view in a tenth of a frame, so the score's
peak is narrower than a frame and interpolating it between integer offsets does not measure the fraction (a
fraction shows as no consistent integer offset). The fraction is measured instead from the matches' motion across
their epipolar lines between a rig's consecutive frames (:mod:`rigsfm.run.checks.subframe`), at the integer
pairing found here; a rig is then named by its whole offset (``rig05 is about +0.5 frame off``). Only the integer
part can pair frames (frames are images); the fraction is reported.

Needs matches on the crowd: flat-shaded persons seen from rigs tens of degrees apart share few features between
narrow views, and then no offset is told (``offsets[r]`` None or no rig ``clear``).
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError
from rigsfm.core.io import load_yaml_or_json
from rigsfm.core.names import name_of, quoted, registered_narrow_images
from rigsfm.core.summary import FrameOffsetsSummary
from rigsfm.run.checks.guided import (
    KEYPOINT_NOISE_PX,
    MIN_MATCHES,
    WIDE_FACTOR,
    band_candidates,
    epipolar_segments,
    guided_matches,
    load_narrow,
    match_line_distances,
    overlapping_pairs,
    pair_features,
)
from rigsfm.run.checks.subframe import (
    NAMED_FRAMES,
    PairFraction,
    SubframeEstimate,
    combine,
    fit_tau,
    measure_pair,
)

logger = logging.getLogger(__name__)

CONSISTENT = 0.6  # share of matches within the band that makes a frame pairing simultaneous
BRUTE_FORCE_RIGS = 8
MIN_SYNC_MATCHES = MIN_MATCHES // 2  # pooled matches below which a pairing gets no score


@dataclass(frozen=True)
class OffsetScore:
    d: int  # narrow a frame k against narrow b frame k + d
    matches: int
    consistent: float | None  # share of the matches within band + keypoint noise; None: too few matches

    def to_dict(self) -> dict:
        return {"d": self.d, "matches": self.matches,
                "consistent": None if self.consistent is None else round(self.consistent, 4)}


@dataclass
class PairSync:
    a: str  # rig names, a < b
    b: str
    scores: list[OffsetScore] = field(default_factory=list)

    def score(self, d: int) -> float | None:
        return next((s.consistent for s in self.scores if s.d == d), None)

    def to_dict(self) -> dict:
        return {"a": self.a, "b": self.b, "scores": [s.to_dict() for s in self.scores]}


@dataclass
class SyncEstimate:
    """Per-rig integer frame offsets (module docstring); ``offsets[r]`` is None where the evidence is not clear
    (no pair consistent at any searched offset: featureless views, or a fraction of a frame off)."""

    offsets: dict[str, int | None]
    pairs: list[PairSync]
    frames_per_rig: dict[str, int]
    max_offset: int
    seconds: float
    skipped: str | None = None
    clear: dict[str, bool] = field(default_factory=dict)  # the rig's offset is backed by consistent pairs
    subframe: SubframeEstimate | None = None  # integer + fraction, where the motion allows

    @property
    def unsynchronised(self) -> dict[str, int]:
        """Rigs clearly off by a non-zero number of frames."""
        return {r: o for r, o in self.offsets.items() if o and self.clear.get(r)}

    @property
    def named(self) -> dict[str, float]:
        """Rigs clearly off in time, by their whole offset: where a fraction was measured, the measured offset
        (named when clear of its error, rigsfm.run.checks.subframe); elsewhere the integer estimate's."""
        measured = self.subframe.offsets if self.subframe else {}
        named = {r: float(o) for r, o in self.unsynchronised.items() if measured.get(r) is None}
        named.update(self.subframe.named if self.subframe else {})
        return named

    @property
    def applicable(self) -> dict[str, int]:
        """The whole frames ``--frame-offsets auto`` pairs frames by: the nearest whole frame of each named rig's
        offset (frames are images; the fraction is reported, not applied)."""
        whole = {r: math.floor(o + 0.5) for r, o in self.named.items()}
        return {r: o for r, o in whole.items() if o}

    def left_after(self, applied: dict[str, int]) -> dict[str, float]:
        """The named rigs still off once ``applied`` pairs the frames (a fraction that cannot be applied)."""
        return {r: o - applied.get(r, 0) for r, o in self.named.items() if abs(o - applied.get(r, 0)) >= NAMED_FRAMES}

    @property
    def warning(self) -> str | None:
        off = self.named
        if not off:
            return None
        rigs = ", ".join(f"{r} is about {_frames(o)} off" for r, o in sorted(off.items()))
        fraction = any(abs(o - round(o)) >= 0.05 for o in off.values())
        return (f"FRAMES NOT SYNCHRONISED: {rigs} (the moving crowd in its narrow images matches the other rigs' "
                "on the epipolar lines only at that shift; frame k of it was taken at the others' frame k + offset): "
                "not a calibration fault; give --frame-offsets auto (or a file 'rig: offset') to pair the frames "
                "by time" + ("; a fraction of a frame cannot be paired away (frames are images): its moving crowd "
                             "stays off the epipolar lines by that fraction's motion" if fraction else ""))

    def fraction_warning(self, applied: dict[str, int]) -> str:
        """The warning once ``applied`` pairs the frames, naming the rigs ``left_after`` it."""
        rigs = ", ".join(f"{r} is about {_frames(self.named[r])} off" for r in sorted(self.left_after(applied)))
        whole = ", ".join(f"{r} {o:+d}" for r, o in sorted(applied.items())) or "none"
        return (f"FRAMES NOT SYNCHRONISED: {rigs}; whole frames applied ({whole}), a fraction of a frame cannot be "
                "(frames are images): the moving crowd in its narrow images stays off the epipolar lines by that "
                "fraction's motion; not a calibration fault")

    def to_dict(self) -> dict:
        return {"offsets": dict(self.offsets), "unsynchronised": self.unsynchronised, "clear": dict(self.clear),
                "named": {r: round(o, 3) for r, o in self.named.items()},
                "applicable": self.applicable,
                "frames_per_rig": dict(self.frames_per_rig), "max_offset": self.max_offset,
                "seconds": round(self.seconds, 3), "skipped": self.skipped, "consistent_share": CONSISTENT,
                "pairs": [p.to_dict() for p in self.pairs],
                "subframe": None if self.subframe is None else self.subframe.to_dict()}


def describe_record(record: FrameOffsetsSummary) -> str:
    """The terminal's line on summary.json's ``frame_offsets``: what was applied, and the offsets estimated with
    their fractions (only whole frames can be applied)."""
    estimate = record.estimate or {}
    applied = ", ".join(f"{rig} {off:+d}" for rig, off in sorted((record.applied or {}).items()))
    sigmas = (estimate.get("subframe") or {}).get("sigmas") or {}
    measured = (estimate.get("subframe") or {}).get("offsets") or {}
    untold = [r for r, o in (estimate.get("offsets") or {}).items() if o is None and measured.get(r) is None]
    why = f"no offset told for {', '.join(untold)}" if untold else "all rigs at 0"
    named = estimate.get("named") or {}
    whole = ", ".join(f"{rig} {_frames(off)}" + (f" (+-{sigmas[rig]:.2f})" if sigmas.get(rig) is not None else "")
                      for rig, off in sorted(named.items()))
    fraction = any(abs(o - round(o)) >= 0.05 for o in named.values())
    return (f"frame offsets ({record.asked}): {'applied ' + applied if applied else f'none applied ({why})'}"
            + (f"; estimated {whole}" if whole else "")
            + ("; a fraction of a frame is not applied (frames are images)" if fraction else ""))


def _frames(offset: float) -> str:
    """+1 frame, +2 frames, +0.5 frame, +1.3 frames (tenths where the offset is not whole)."""
    whole = round(offset)
    text = f"{whole:+d}" if abs(offset - whole) < 0.05 else f"{offset:+.1f}"
    return f"{text} frame{'s' if abs(offset) >= 1.05 or abs(whole) > 1 else ''}"


def rig_frames(reconstruction: pycolmap.Reconstruction) -> dict[str, list[pycolmap.Image | None]]:
    """Rig -> its registered narrow images by frame: a rig's frame index is the position of the frame's name among
    the names of all its images (wide or narrow, in frame-name order), None where the frame has no registered
    narrow image, so that a narrow image missing or not registered does not move the rig's later frames."""
    names: dict[str, set[str]] = {}
    for image in reconstruction.images.values():
        parsed = name_of(image)
        names.setdefault(parsed.rig, set()).add(parsed.frame)
    narrow: dict[str, dict[str, pycolmap.Image]] = {}
    for image in registered_narrow_images(reconstruction):
        parsed = name_of(image)
        narrow.setdefault(parsed.rig, {})[parsed.frame] = image
    return {rig: [images.get(frame) for frame in sorted(names[rig])] for rig, images in sorted(narrow.items())}


def frames_by_time(reconstruction: pycolmap.Reconstruction,
                   offsets: dict[str, int]) -> dict[str, list[pycolmap.Image]]:
    """Like ``synchronised_frames`` but grouping rig r's k-th frame's narrow image at time ``k + offsets[r]``: label ->
    images of that instant (two or more rigs). The label is the frame name of a rig at offset 0 where one has it."""
    by_time: dict[int, list[pycolmap.Image]] = {}
    for rig, frames in rig_frames(reconstruction).items():
        for k, image in enumerate(frames):
            if image is not None:
                by_time.setdefault(k + int(offsets.get(rig, 0)), []).append(image)
    grouped = {}
    for t, images in sorted(by_time.items()):
        if len({name_of(im).rig for im in images}) < 2:
            continue
        at_zero = [name_of(im).frame for im in images if not offsets.get(name_of(im).rig, 0)]
        grouped[at_zero[0] if at_zero else f"time {t}"] = images
    return grouped


def search_tolerance(band: float) -> float:
    """The lateral tolerance the matches of a frame pairing are searched within: ``WIDE_FACTOR`` x band + keypoint
    noise, and at least ``WIDE_FACTOR`` x keypoint noise, so that matches spread over it (not simultaneous) fill
    band + keypoint noise (the score's) only as a small share of it even where the band is under a pixel."""
    return max(WIDE_FACTOR * band + KEYPOINT_NOISE_PX, WIDE_FACTOR * KEYPOINT_NOISE_PX)


def _distances_for(first, second, f_ji: np.ndarray, band: float, floor_frame: bool) -> np.ndarray:
    """Distances (px) of the guided matches of two narrow images from their epipolar lines."""
    fi, fj = pair_features(first, second)
    if fi is None or fj is None or len(fi.xy) < 2 or len(fj.xy) < 2:
        return np.zeros(0)
    lines = np.c_[fi.undistorted, np.ones(len(fi.undistorted))] @ f_ji.T
    segments = epipolar_segments(first.image, second.image, fi.undistorted, floor_frame)
    candidates = band_candidates(f_ji, lines, fj.undistorted, segments, search_tolerance(band))
    matches = guided_matches(fi, fj, candidates.a, candidates.b)
    return match_line_distances(lines, fj, matches) if len(matches) else np.zeros(0)


def _solve(rigs: list[str], pairs: list[PairSync], max_offset: int) -> dict[str, int]:
    """Integer offsets maximising the pairs' summed scores at d = o_a - o_b (module docstring)."""
    index = {r: n for n, r in enumerate(rigs)}
    values = np.arange(-max_offset, max_offset + 1)
    tables = []
    for pair in pairs:
        table = np.zeros(4 * max_offset + 1)  # by d + 2 max_offset
        for s in pair.scores:
            table[s.d + 2 * max_offset] = s.consistent or 0.0
        tables.append((index[pair.a], index[pair.b], table))

    def total(assignment: np.ndarray) -> np.ndarray:  # assignment: (..., rigs)
        return sum(t[assignment[..., a] - assignment[..., b] + 2 * max_offset] for a, b, t in tables)

    if len(rigs) <= BRUTE_FORCE_RIGS:
        rest = np.array(list(itertools.product(values, repeat=len(rigs) - 1)), dtype=int).reshape(-1, len(rigs) - 1)
        assignments = np.c_[np.zeros(len(rest), int), rest]
        scores = total(assignments) if tables else np.zeros(len(assignments))
        # ties: the assignment nearest all-zero
        best = assignments[np.lexsort((np.abs(assignments).sum(axis=1), -scores))[0]]
    else:
        best = np.zeros(len(rigs), int)
        for _ in range(10):
            before = best.copy()
            for r in range(1, len(rigs)):
                trials = np.repeat(best[None], len(values), axis=0)
                trials[:, r] = values
                best = trials[int(np.argmax(total(trials)))]
            if (best == before).all():
                break
    counts = {int(v): int((best == v).sum()) for v in set(best.tolist())}
    shift = min(counts, key=lambda v: (-counts[v], v != 0, abs(v)))
    shifted = best - shift
    if np.abs(shifted).max(initial=0) > max_offset:  # the gauge would leave the searched range: keep rig 1 at 0
        shifted = best
    return {r: int(shifted[index[r]]) for r in rigs}


def estimate_frame_offsets(reconstruction: pycolmap.Reconstruction, image_dir: Path, narrow_poses: dict, *,
                           max_offset: int = 2, frames_per_offset: int = 2, sift_size: int = 800,
                           warp_height_m: float = 0.0) -> SyncEstimate:
    """Per-rig frame offsets of the narrow images (module docstring), with the ``F_ji`` and bands of
    ``narrow_poses`` (narrow_poses.json of this model)."""
    start = time.perf_counter()
    world = narrow_poses.get("world") or {}
    floor_frame = world.get("frame") == "floor" and bool(narrow_poses.get("metric"))
    per_rig = rig_frames(reconstruction)
    counts = {r: len(images) for r, images in per_rig.items()}
    rigs = list(per_rig)
    if len(rigs) < 2 or min(counts.values(), default=0) < 2:
        return SyncEstimate({r: None for r in rigs}, [], counts, max_offset, time.perf_counter() - start,
                            "needs narrow images of two or more rigs with two or more frames each")
    max_offset = max(0, min(max_offset, min(counts.values()) - 1))
    by_pair = {(p["i"], p["j"]): p for p in narrow_poses.get("pairs", [])}
    first_frames = [next(im for im in images if im is not None) for images in per_rig.values()]
    overlapping = {tuple(sorted((name_of(reconstruction.find_image_with_name(i)).rig,
                                 name_of(reconstruction.find_image_with_name(j)).rig)))
                   for i, j in overlapping_pairs(reconstruction, first_frames, floor_frame)}
    cache: dict[str, object] = {}

    def both(a: str, b: str, k: int, d: int) -> bool:
        return per_rig[a][k] is not None and per_rig[b][k + d] is not None

    def name(rig: str, k: int) -> str:  # of a frame that has its narrow image (``both``)
        image = per_rig[rig][k]
        assert image is not None
        return image.name

    def loaded(image: pycolmap.Image | None):
        if image is None:
            return None
        if image.name not in cache:
            cache[image.name] = load_narrow(image, Path(image_dir), warp_height_m if floor_frame else None, sift_size)
        return cache[image.name]

    pairs = []
    for a, b in sorted(overlapping):
        pair = PairSync(a, b)
        for d in range(-max_offset, max_offset + 1):
            ks = [k for k in range(counts[a]) if 0 <= k + d < counts[b] and both(a, b, k, d)][:max(1, frames_per_offset)]
            pooled = []
            for k in ks:
                image_i, image_j = per_rig[a][k], per_rig[b][k + d]
                entry = by_pair.get((name(a, k), name(b, k + d)))
                band = None if entry is None else entry.get("epipolar_band_95_px")
                if band is None or not math.isfinite(band):
                    continue
                first, second = loaded(image_i), loaded(image_j)
                if first is None or second is None:
                    continue
                fundamental = np.asarray(entry["F_ji"], dtype=np.float64)  # type: ignore[index]  # a band: entry is set
                distances = _distances_for(first, second, fundamental, band, floor_frame)
                pooled.append(distances / (band + KEYPOINT_NOISE_PX))
            distances = np.concatenate(pooled) if pooled else np.zeros(0)
            share = float(np.mean(distances <= 1.0)) if len(distances) >= MIN_SYNC_MATCHES else None
            pair.scores.append(OffsetScore(d, len(distances), share))
            logger.info("sync %s frame k <-> %s frame k%+d: %d matches, %s within the band", a, b, d, len(distances),
                        "-" if share is None else f"{100 * share:.0f} %")
        pairs.append(pair)
    offsets = _solve(rigs, pairs, max_offset)
    clear = {}
    for rig in rigs:
        moved = dict(offsets, **{rig: 0})
        # a rig at 0 is told only where a pair is not consistent a frame away (too few matches or off the lines):
        # in a still crowd every pairing is, and 0 (the solver's tie) was told, 'all rigs at 0', whatever the truth
        shifted = [dict(offsets, **{rig: s}) for s in (-1, 1)]
        clear[rig] = any((p.score(offsets[p.a] - offsets[p.b]) or 0.0) >= CONSISTENT
                         and ((p.score(moved[p.a] - moved[p.b]) or 0.0) < CONSISTENT if offsets[rig] else
                              any(_measured_unlike(p, o[p.a] - o[p.b]) for o in shifted))
                         for p in pairs if rig in (p.a, p.b))
    fractions, refining = [], time.perf_counter()
    for a, b in sorted(overlapping):
        d = offsets[a] - offsets[b]
        ks = [k for k in range(counts[a]) if 0 <= k + d < counts[b] and both(a, b, k, d)][:max(1, frames_per_offset)]
        if not ks:
            fractions.append(PairFraction(a, b, d, None, None, 0, 0, "no frames of both rigs at that pairing"))
            continue
        entry = by_pair.get((name(a, ks[0]), name(b, ks[0] + d)))
        band = None if entry is None else entry.get("epipolar_band_95_px")
        if band is None or not math.isfinite(band):
            fractions.append(PairFraction(a, b, d, None, None, 0, 0, "no band"))
            continue
        s, g, tracked = [], [], 0
        for k in ks:
            j = k + d
            frames = [loaded(per_rig[b][i]) if 0 <= i < counts[b] else None for i in (j - 1, j, j + 1)]
            first = loaded(per_rig[a][k])
            if first is None or frames[1] is None:
                continue
            f_ji = np.asarray(by_pair[(name(a, k), name(b, j))]["F_ji"], dtype=np.float64)
            signed, motion, n = measure_pair(first, frames, pair_features, f_ji, band, floor_frame)
            s.append(signed)
            g.append(motion)
            tracked += n
        tau, sigma, inliers, why = fit_tau(np.concatenate(s) if s else np.zeros(0),
                                           np.concatenate(g) if g else np.zeros(0), band)
        fractions.append(PairFraction(a, b, d, tau, sigma, tracked, inliers, why))
        logger.info("sync %s frame k <-> %s frame k%+d%s: %d tracked matches, %d inliers%s", a, b, d,
                    "" if tau is None else f"{tau:+.3f} (+-{sigma:.3f})", tracked, inliers,
                    f" ({why})" if why else "")
    subframe = combine(rigs, offsets, fractions) if fractions else None
    if subframe is not None:
        subframe.seconds = time.perf_counter() - refining
    estimate = SyncEstimate({r: (offsets[r] if clear[r] else None) for r in rigs}, pairs, counts, max_offset,
                            time.perf_counter() - start, None if pairs else "no two rigs' narrow footprints overlap",
                            clear, subframe)
    logger.info("frame offsets: %s, with fractions %s (%.1f s)", estimate.offsets,
                estimate.subframe and estimate.subframe.offsets, estimate.seconds)
    return estimate


def _measured_unlike(pair: PairSync, d: int) -> bool:
    """The pair was matched at ``d`` (within the offsets tried) and is not consistent there (too few matches, or
    matches off the lines)."""
    return any(s.d == d and (s.consistent or 0.0) < CONSISTENT for s in pair.scores)


def read_frame_offsets(path: Path, rigs: list[str], frames_per_rig: dict[str, int]) -> dict[str, int]:
    """A frame-offsets file (``rig03: 1``, one rig a line, integer frames; unnamed rigs are at 0), checked against
    the rigs and the recording's length; an ``InputError`` naming the rig and the fix otherwise."""
    path = Path(path)
    data = load_yaml_or_json(path, "frame offsets", form="write one line per rig that is off, '<rig>: <whole "
                             "frames>' with a space after the colon (e.g. 'rig03: 1')")
    offsets = {}
    for rig, value in data.items():
        rig = str(rig)
        if rig not in rigs:
            raise InputError(f"{path}: rig {rig!r} is not in rigs.yaml ({quoted(rigs)}); fix its name or remove "
                             "the line")
        if isinstance(value, float) and value.is_integer():  # '1.0' is a whole number of frames
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{path}: the offset of rig '{rig}' must be a whole number of frames (e.g. '{rig}: 1'), got "
                             f"{value!r}")
        frames = frames_per_rig.get(rig, 0)
        if value and not frames:
            raise InputError(f"{path}: rig '{rig}' has no narrow images, so no offset applies to it; remove the line")
        if abs(value) >= max(frames, 1):
            raise InputError(f"{path}: the offset {value:+d} of rig '{rig}' is beyond the recording ({frames} narrow "
                             f"frame(s) of '{rig}': offsets {-(frames - 1)}..{frames - 1}); fix the offset")
        offsets[rig] = value
    return offsets
