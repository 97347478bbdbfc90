"""Whether a recording's rigs took their frames together, from the persons themselves (``rigsfm associate``).

A rig whose frames are late shows each walker where it will be, not where the other views see it, so its heads
fall off the persons the others triangulate. A tested frame is associated again with one rig's detections taken
from its own frame k + s (s in -search..search), the others' unchanged, from the same carried state: every shift is
a whole association with the rig in it, so its own view takes part in choosing the persons alike at every shift (an
association keeps the persons a view's detections confirm: a comparison with the rig in some shifts and not in
others would favour its own frame). The rig's detections in confident persons (three or more views, a positive
score), summed over the tested frames, peak at the shift that makes it simultaneous; its offset is minus that shift
(the convention of ``rigsfm run --frame-offsets``: rig03 +1 took its frame k at the others' frame k + 1).
Measured on rendered crowds: benchmarks/README.md, *Frame offsets from the user's heads*.
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import logging
import math
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigsfm.associate.detections import Detections
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.rows import confident_rows
from rigsfm.associate.solve import associate_views
from rigsfm.core.names import ImageName
from rigsfm.run.checks.sync import _frames, read_frame_offsets

logger = logging.getLogger(__name__)

SEARCH = 2  # whole frames searched either way
NOT_A_RECORDING = "three frames and three narrow views are needed"  # skipped, not asked: nothing to say
TESTED_FRAMES = 4  # carried frames tested: each costs 1 + cameras x 2 SEARCH associations


class Correction(enum.StrEnum):
    """How a tested association corrects its views' poses (rigsfm.run.narrow.timing's docstring says each)."""

    CONFIRM = "confirm"  # carried, then the doubted rigs counted again correcting themselves
    CARRY = "carry"  # each view's correction from the frame before
    SELF = "self"  # each association its own
    OWN = "own"  # carried, except the tested rig's
    NONE = "none"


# A rig is named where its best shift's count exceeds the count at 0 by this many sigmas (the two counts taken as
# independent Poisson counts: an overstated sigma, they share most persons); on the rendered crowds a synchronised
# rig's count a frame away was 0.67-0.87x its count at 0 at 10 fps, a third at 2 fps (benchmarks/README.md).
Z_NAMED = 2.0
Z_TELLS = 2.0  # the median camera's peak over its next best shift, in the same sigmas: the crowd tells time


@dataclass
class RigTiming:
    camera: str
    counts: dict[int, int]  # per shift s: its detections in confident persons, summed over the tested frames
    offset: int | None  # its frame k was taken at the others' frame k + offset; None: not told (no clear peak)
    z: float  # the best shift's count above the count at 0, in sigmas (0 where 0 is best)
    # where its counts under the carried corrections peaked away from 0 (:func:`confirmed_counts`): those counts
    carried: dict[int, int] | None = None

    def to_dict(self) -> dict:
        out = {"camera": self.camera, "confident_detections": {f"{s:+d}": c for s, c in sorted(self.counts.items())},
               "offset": self.offset, "z": round(self.z, 2)}
        if self.carried is not None:
            out["carried_confident_detections"] = {f"{s:+d}": c for s, c in sorted(self.carried.items())}
        return out


@dataclass
class SyncCheck:
    """The check of a recording's timing (module docstring); ``asked``: check (the default), auto or the file."""

    asked: str
    frames: list[str] = field(default_factory=list)  # the tested frames
    search: int = 0
    rigs: dict[str, RigTiming] = field(default_factory=dict)
    skipped: str | None = None  # why nothing was tested
    applied: dict[str, int] = field(default_factory=dict)  # the offsets the frames were paired by
    seconds: float = 0.0

    @property
    def named(self) -> dict[str, int]:
        """Rigs clearly off in time, by their whole offset."""
        return {r: t.offset for r, t in self.rigs.items() if t.offset}

    @property
    def warning(self) -> str | None:
        off = {r: o for r, o in self.named.items() if o != self.applied.get(r, 0)}
        if not off:
            return None
        hint = ("; the offsets applied were not these" if self.applied else
                "; give --frame-offsets auto (or a file 'rig: offset') to pair the frames by time")
        return not_synchronised(off, "not a detection or calibration fault, and its persons are missed or wrong until "
                                     f"the frames are paired by time{hint}")

    def to_dict(self) -> dict:
        return {"asked": self.asked, "tested_frames": list(self.frames), "search": self.search,
                "named": dict(self.named), "applied": dict(self.applied), "skipped": self.skipped,
                "seconds": round(self.seconds, 3), "z_named": Z_NAMED, "z_tells": Z_TELLS,
                "rigs": {r: t.to_dict() for r, t in sorted(self.rigs.items())}}


def not_synchronised(off: dict[str, int], consequence: str) -> str:
    """The warning on rigs named off in time (rig -> offset), ``consequence`` what it means for this command."""
    rigs = ", ".join(f"{r} is about {_frames(o)} off" for r, o in sorted(off.items()))
    return (f"FRAMES NOT SYNCHRONISED: {rigs} (its heads meet the other views' persons best at that shift: frame k "
            f"of it was taken at the others' frame k + offset): {consequence}")


def describe(record: dict) -> str:
    """The terminal's line on a check's record (:meth:`SyncCheck.to_dict`): what was tested, named and applied."""
    if record.get("skipped"):
        what = "applied " + ", ".join(f"{r} {o:+d}" for r, o in sorted(record["applied"].items())) \
            if record.get("applied") else (f"not checked ({record['skipped']}): whether the rigs took their frames "
                                            "together is unknown")
        return f"frame offsets ({record['asked']}): {what}"
    rigs = record.get("rigs") or {}
    untold = sorted(r for r, t in rigs.items() if t["offset"] is None)
    if rigs and len(untold) == len(rigs):  # the crowd's persons do not time these views: nothing is known
        return (f"frame offsets ({record['asked']}): not told (the persons of {len(record['tested_frames'])} frame(s) "
                f"peak at no shift clearly, {record['seconds']:.1f} s): whether the rigs are synchronised is unknown")
    named = ", ".join(f"{r} {_frames(o)}" for r, o in sorted(record["named"].items()))
    applied = ", ".join(f"{r} {o:+d}" for r, o in sorted(record["applied"].items()))
    return (f"frame offsets ({record['asked']}): " + (f"estimated {named}" if named else "all rigs at 0")
            + (f" ({', '.join(untold)} not told)" if untold else "")
            + f" over {len(record['tested_frames'])} frame(s), {record['seconds']:.1f} s"
            + (f"; frames paired by time: {applied}" if applied else ""))


def image_index(detections: Detections) -> tuple[list[str], dict[tuple[str, str], str]]:
    """The frames in order, and per (camera, frame) its image name."""
    names = {(ImageName.parse(n).camera, ImageName.parse(n).frame): n for n in detections.images}
    return sorted({f for _, f in names}), names


def frames_per_rig(detections: Detections) -> dict[str, int]:
    frames: dict[str, set[str]] = {}
    for name in detections.images:
        parsed = ImageName.parse(name)
        frames.setdefault(parsed.rig, set()).add(parsed.frame)
    return {r: len(f) for r, f in frames.items()}


def given_offsets(path: Path, detections: Detections, rigs: Iterable[str]) -> dict[str, int]:
    """--frame-offsets FILE, checked against the run's rigs (``rigs``: those with a narrow image) and the
    DETECTIONS' frames (``rigsfm run``'s file and rules)."""
    counts = frames_per_rig(detections)
    return {r: o for r, o in read_frame_offsets(path, sorted(set(rigs)), counts).items() if o}


def recording_frames(detections: Detections, images_root: Path | None = None, known: Iterable[str] = ()) -> list[str]:
    """The recording's frames in order: the DETECTIONS' and the run's (``known`` image names), and where the run's
    images folder holds the detected rigs' narrow images, theirs: a DETECTIONS of every second frame counts its
    offsets in the recording's frames, not its own."""
    from rigsfm.run.inputs.images import IMAGE_SUFFIXES

    frames = {ImageName.parse(n).frame for n in detections.images}
    rigs = {ImageName.parse(n).rig for n in detections.images}
    for name in known:
        try:
            parsed = ImageName.parse(name)
        except ValueError:
            continue
        if parsed.is_narrow and parsed.rig in rigs:
            frames.add(parsed.frame)
    if images_root is not None:
        for rig in rigs:
            try:
                frames.update(p.name for p in (Path(images_root) / rig / "narrow").iterdir()
                              if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            except OSError:
                continue  # not there (moved, or the frames only in DETECTIONS): the DETECTIONS' frames count
    return sorted(frames)


def skipped_frames(detections: Detections, recording: list[str]) -> list[str]:
    """The recording's frames between the DETECTIONS' first and last that the DETECTIONS do not hold."""
    frames = image_index(detections)[0]
    if not frames:
        return []
    first, last = recording.index(frames[0]), recording.index(frames[-1])
    return [f for f in recording[first:last + 1] if f not in set(frames)]


def paired_frames(detections: Detections, offsets: dict[str, int], recording: list[str] | None = None,
                  ) -> list[tuple[str, list[str]]]:
    """The frames with each rig's images paired by time: a rig off by o joins its frame j to the others' frame
    j + o, counted in the ``recording``'s frames (:func:`recording_frames`; None: the DETECTIONS' own); frames that
    would fall outside the recording, or on a frame the DETECTIONS do not hold, are left out: nobody's frame took
    them."""
    frames, names = image_index(detections)
    recording = frames if recording is None else recording
    groups: dict[str, list[str]] = {f: [] for f in frames}
    for (camera, frame), name in names.items():
        j = recording.index(frame) + offsets.get(camera.split("/")[0], 0)
        if 0 <= j < len(recording) and recording[j] in groups:
            groups[recording[j]].append(name)
    return [(f, sorted(g)) for f, g in groups.items() if g]


def camera_bands(bands: dict[tuple[str, str], float]) -> dict[tuple[str, str], float]:
    """(camera a, camera b) -> a band of two of their images, both ways (a static rig's band holds in every
    frame)."""
    out: dict[tuple[str, str], float] = {}
    for (a, b), band in bands.items():
        if band is not None and math.isfinite(float(band)):
            ca, cb = ImageName.parse(a).camera, ImageName.parse(b).camera
            out.setdefault((ca, cb), float(band))
            out.setdefault((cb, ca), float(band))
    return out


def with_camera_bands(model, groups: Iterable[list[str]]):
    """``model`` with a band for every two images of a group of different cameras taken in different frames: their
    cameras' band (:func:`camera_bands` of its frames' own bands: a frame's band between two cameras of static rigs
    holds in every frame)."""
    by_cameras = camera_bands({(a, b): band for (a, b), band in model.bands.items()
                               if ImageName.parse(a).frame == ImageName.parse(b).frame})
    bands = dict(model.bands)
    for group in groups:
        cameras = [ImageName.parse(n).camera for n in group]
        for a, ca in zip(group, cameras):
            for b, cb in zip(group, cameras):
                if ca != cb and (a, b) not in bands and (ca, cb) in by_cameras:
                    bands[(a, b)] = by_cameras[(ca, cb)]
    return dataclasses.replace(model, bands=bands)


def tested_frames(frames: list[str], search: int, complete) -> list[int]:
    """The first ``TESTED_FRAMES`` frames (indices) with ``search`` frames either way whose ``complete(i)`` holds
    (every view there, and whatever else the caller needs)."""
    return [i for i in range(max(1, search), len(frames) - search) if complete(i)][:TESTED_FRAMES]


def check_frame_offsets(model, detections: Detections, chain: list, options: AssociateOptions, asked: str,
                        applied: dict[str, int] | None = None, recording: list[str] | None = None,
                        correct: Correction = Correction.CARRY) -> SyncCheck:
    """Each rig's frame offset (module docstring) from ``chain`` (associate_frames' frames of ``detections``, in
    order, paired as given: ``applied`` offsets already applied, none by default); ``recording``: its frames
    (:func:`recording_frames`, where the caller has them). ``correct``: the views' corrections carried from the
    chain's frame before (``carry``), or ``confirm`` (:func:`confirmed_counts`, ``rigsfm run``'s way; not the
    default: on the rendered crowds it named no more late rigs, one at a wrong offset, at many times the CPU, the
    self-calibrating associations being the costly ones: benchmarks/README.md)."""
    from rigsfm.associate.pipeline import frame_views

    start = time.perf_counter()
    check = SyncCheck(asked, applied=dict(applied or {}))
    frames, names = image_index(detections)
    if applied:
        check.skipped = "the frames were paired by the offsets applied"
        return check
    cameras = sorted({c for c, _ in names})
    search = min(SEARCH, (len(frames) - 1) // 2)
    chained = {f.frame: k for k, f in enumerate(chain)}
    if len(cameras) < 3 or search < 1:
        check.skipped = NOT_A_RECORDING
        return check
    if recording is None:
        recording = recording_frames(detections, model.images_root, model.known)
    skipped = skipped_frames(detections, recording)
    if skipped:  # the shifts below step through the DETECTIONS' frames: every second one would count double
        check.skipped = (f"the detections skip {len(skipped)} frame(s) of the recording (e.g. {skipped[0]}), and the "
                         "check needs consecutive frames")
        return check

    def testable(i: int) -> bool:
        before = chain[chained[frames[i - 1]]] if frames[i - 1] in chained else None
        carried = {ImageName.parse(v.name).camera for v in before.views if v.band_sigma_px is not None} \
            if before is not None else set()
        return carried >= set(cameras) and all((c, frames[j]) in names for c in cameras
                                                for j in range(i - search, i + search + 1))

    tested = tested_frames(frames, search, testable)
    if not tested:
        check.skipped = "no frame with every narrow view in the frames around it"
        return check
    check.frames, check.search = [frames[i] for i in tested], search
    if options.pixel_sigma is None:  # the detector's noise the chain found: its self-correcting counts start there
        options = dataclasses.replace(options, pixel_sigma=next(
            (f.result.pixel_sigma for f in chain if f.result.pixel_sigma is not None), None))
    windows = []
    for i in tested:
        window = [names[(c, frames[j])] for c in cameras for j in range(i - search, i + search + 1)]
        trial_model = with_camera_bands(model, [window])
        templates = {}
        for j in range(i - search, i + search + 1):
            for view in frame_views(trial_model, detections, frames[j], [names[(c, frames[j])] for c in cameras]):
                templates[(ImageName.parse(view.name).camera, j - i)] = view
        before = chain[chained[frames[i - 1]]]
        windows.append((templates, {ImageName.parse(v.name).camera: v for v in before.views}, before.result))
    carried: dict[str, dict[int, int]] = {}
    if correct == Correction.CONFIRM:
        counts, carried = confirmed_counts(windows, cameras, search, options)
    else:
        counts = shift_counts(windows, cameras, search, options)
    for templates, _, _ in windows:
        for view in templates.values():
            view.grey = None
    check.rigs = rig_timings(counts, carried)
    check.seconds = time.perf_counter() - start
    logger.info("frame offsets: %s over %s (%.1f s)", {r: t.counts for r, t in check.rigs.items()}, check.frames,
                check.seconds)
    return check


def shift_counts(windows: list, cameras: list[str], search: int, options: AssociateOptions,
                 own_pose: bool = False, only: list[str] | None = None) -> dict[str, dict[int, int]]:
    """Per camera and shift s, its detections in confident persons, summed over ``windows``: each (templates, carried,
    earlier): per (camera, s) the camera's view of the tested frame's k + s, per camera its view of the frame before
    (whose shift it carries), and the frame before's persons; carried None: each association corrects its views'
    poses itself. ``own_pose``: the tested camera carries its head size but not its pose correction, at every shift
    (0 included: one association per camera and shift), the others carry theirs: a late rig's correction carried
    from the frame before was fitted to its heads a frame away (``rigsfm run``'s heads, rigsfm.run.narrow.timing).
    ``only``: these cameras tested and counted (default: all)."""
    tested_cameras = cameras if only is None else [c for c in cameras if c in only]
    counts = {c: dict.fromkeys(range(-search, search + 1), 0) for c in tested_cameras}
    for templates, carried, earlier in windows:
        for tested in tested_cameras if own_pose else [None, *tested_cameras]:
            for s in range(-search, search + 1):
                if not own_pose and (tested is None) != (s == 0):
                    continue
                views = [copy.copy(templates[(c, s if c == tested else 0)]) for c in cameras]
                if carried is not None:
                    for view, camera in zip(views, cameras):
                        if own_pose and camera == tested:
                            view.head_px = carried[camera].head_px
                        else:
                            view.carry(carried[camera])
                result = associate_views(views, options, carried=carried is not None, earlier=earlier)
                confident = confident_rows(result.members, result.scores, options.self_calibration_min_score)
                for v, camera in enumerate(cameras):
                    if camera in counts and (tested is None or camera == tested):
                        counts[camera][s] += int(np.sum(confident & (result.members[:, v] >= 0)))
    return counts


def best_shift(counts: dict[int, int]) -> int:
    """The shift of the largest count (the nearest to 0 among equals)."""
    return max(counts, key=lambda s: (counts[s], -abs(s)))


def confirmed_counts(windows: list, cameras: list[str], search: int, options: AssociateOptions,
                     own_pose: bool = False) -> tuple[dict[str, dict[int, int]], dict[str, dict[int, int]]]:
    """:func:`shift_counts` under the views' carried corrections, then again, each association correcting its
    views itself, for the cameras whose carried count peaks away from 0 (doubted): a late rig's correction carried
    from the frame before was fitted to its heads a frame away, which hides its peak, while correcting every
    association itself for every camera costs several times the CPU. Returns the counts (the doubted cameras' their
    own) and the doubted cameras' carried counts. ``own_pose``: the recount carries the others' corrections and
    not the doubted camera's (:func:`shift_counts`), instead of every view correcting itself."""
    counts = shift_counts(windows, cameras, search, options)
    doubted = [c for c, n in counts.items() if best_shift(n) != 0]
    if not doubted:
        return counts, {}
    own = shift_counts(windows if own_pose else [(t, None, None) for t, _, _ in windows], cameras, search, options,
                       own_pose=own_pose, only=doubted)
    return {**counts, **own}, {c: counts[c] for c in doubted}


def timings(counts: dict[str, dict[int, int]]) -> dict[str, RigTiming]:
    """Per camera its offset from :func:`shift_counts`: minus the best shift, where it is 0 or clear of 0 by
    ``Z_NAMED``; None (not told) where another shift leads without being clear, and for every camera where the
    crowd does not tell time (:func:`tells_time`)."""
    told = tells_time(counts)
    out = {}
    for camera, c in counts.items():
        best = best_shift(c)
        z = (c[best] - c[0]) / math.sqrt(max(c[best] + c[0], 1))
        offset = None if not told else 0 if best == 0 else (-best if z >= Z_NAMED else None)
        out[camera] = RigTiming(camera, c, offset, z)
    return out


def rig_timings(counts: dict[str, dict[int, int]], carried: dict[str, dict[int, int]] | None = None,
                ) -> dict[str, RigTiming]:
    """Per rig its :func:`timings`, with the carried counts of the cameras counted again (:func:`confirmed_counts`)."""
    out = {}
    for camera, timing in timings(counts).items():
        timing.carried = (carried or {}).get(camera)
        out[camera.split("/")[0]] = timing
    return out


def tells_time(counts: dict[str, dict[int, int]]) -> bool:
    """Whether the persons time these views at all: most cameras' counts peak clearly (their best shift ahead of the
    next by ``Z_TELLS``). Where the association finds few persons of three views, or they are mostly chance groups,
    the counts are flat in the shift and a chance excess would name a rig (seen on a 4-rig crowd on a 120 degree arc)."""
    leads = []
    for c in counts.values():
        first, second = sorted(c.values(), reverse=True)[:2]
        leads.append((first - second) / math.sqrt(max(first + second, 1)))
    return bool(leads) and float(np.median(leads)) >= Z_TELLS
