"""``rigsfm associate``: detections of several synchronised narrow cameras -> 3D persons, per frame."""

from __future__ import annotations

import copy
import dataclasses
import itertools
import json
import logging
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.associate.appearance import read_grey
from rigsfm.associate.detections import Detections, read_detections
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.shifts import _confident
from rigsfm.associate.solve import FrameResult, associate_views
from rigsfm.associate.trajectories import Links, tracks
from rigsfm.associate.views import View, view_pose_sigmas
from rigsfm.core.errors import InputError
from rigsfm.core.io import file_sha256
from rigsfm.core.names import ImageName, quoted
from rigsfm.core.summary import Summary
from rigsfm.core.workspace import Workspace, model_fingerprint
from rigsfm.run.matching.reuse import recorded_contents

logger = logging.getLogger(__name__)


@dataclass
class RunModel:
    """What association needs from a finished run: its narrow images and the pairs' 95 % bands."""

    images: dict[str, pycolmap.Image]  # registered narrow images
    bands: dict[tuple[str, str], float]
    known: set[str]  # every image name of the run's inputs (registered or not)
    world: dict | None
    centre_sigma_m: dict[str, float] = field(default_factory=dict)  # per narrow image, 1 sigma of its centre
    # per narrow image, its centre's 3x3 covariance (m^2, world axes), where the run delivers it
    centre_covariance_m2: dict[str, np.ndarray] = field(default_factory=dict)
    images_root: Path | None = None  # where the run read its images (the appearance cue), None: unknown
    image_sha256: dict[str, str] = field(default_factory=dict)  # the content the run was made from (images.json)
    # an image the run was not given -> the run's image whose pose and bands it takes (``--poses-from``)
    stand_ins: dict[str, str] = field(default_factory=dict)
    # the images whose appearance was refused and said so: once per command (dataclasses.replace keeps this set)
    images_said: set[str] = field(default_factory=set)


def load_run(out: Path) -> RunModel:
    workspace = Workspace(out)
    workspace.require_result()
    reconstruction = workspace.read_sparse()
    poses = workspace.read_narrow_poses()
    images = {}
    for image in reconstruction.images.values():
        try:
            name = ImageName.parse(image.name)
        except ValueError:
            continue
        if name.is_narrow and image.has_pose:
            images[image.name] = image
    bands = {}
    for pair in poses.get("pairs", []):
        band = pair.get("epipolar_band_95_px")
        if band is not None:
            bands[(pair["i"], pair["j"])] = float(band)
            bands[(pair["j"], pair["i"])] = float(band)
    known = {image.name for image in reconstruction.images.values()} | set(images)
    centres, covariances = {}, {}
    images_root = None
    try:
        summary = Summary.from_json(json.loads(workspace.summary.read_text(encoding="utf-8")))
        root = summary.inputs.images
        images_root = Path(root) if isinstance(root, str) and root and Path(root).is_dir() else None
        if summary.uncertainty is None:
            raise KeyError("uncertainty")
        narrow = summary.uncertainty.narrow
        # in the model's unit: metres, or the mapper's unit where the run is not metric (its _mm keys null)
        centres = {image_name: float(sigma) for image_name, entry in narrow.items()
                   if (sigma := entry.centre_sigma_in_model_units()) is not None}
        for image_name, entry in narrow.items():
            matrix, per = entry.centre_covariance_mm2, 1e-6
            if matrix is None:
                matrix, per = entry.centre_covariance_units2, 1.0
            if image_name in images and matrix is not None:
                # delivered in the camera's axes: back to the world's through the delivered pose
                axes = images[image_name].cam_from_world().rotation.matrix()
                covariances[image_name] = per * axes.T @ np.asarray(matrix, dtype=np.float64).reshape(3, 3) @ axes
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        logger.warning("%s holds no camera centre uncertainty; the persons' covariances leave it out",
                       workspace.summary)
    return RunModel(images, bands, known, poses.get("world"), centres, covariances, images_root,
                    recorded_contents(workspace.image_contents))


def _frame_images(model: RunModel, frame: str) -> dict[str, str]:
    """Per camera (``<rig>/narrow``), the name of the run's registered narrow image of ``frame``."""
    return {ImageName.parse(n).camera: n for n in model.images if ImageName.parse(n).frame == frame}


def frame_sizes(model: RunModel, frame: str) -> dict[str, tuple[int, int]]:
    """Per camera (``<rig>/narrow``), the image size of the run's registered narrow image of ``frame``: the poses
    ``--poses-from`` lends to frames the run was not given."""
    # a model's images have cameras
    sizes = {camera: (model.images[name].camera.width, model.images[name].camera.height)  # type: ignore[union-attr]
             for camera, name in _frame_images(model, frame).items()}
    if not sizes:
        frames = sorted({ImageName.parse(name).frame for name in model.images})
        named = [f for f in frames if Path(f).stem == Path(frame).stem]  # the name given without its extension
        hint = f" (did you mean {quoted(named[:1])}?)" if named else ""
        raise InputError(f"--poses-from {frame!r} is not a frame of this run with a registered narrow image{hint}; "
                         f"its frames: {quoted(frames[:8])}{' ...' if len(frames) > 8 else ''}")
    return sizes


def with_stand_ins(model: RunModel, names: Iterable[str], frame: str) -> RunModel:
    """``model`` with an image for each of ``names`` the run does not hold: its camera's image of the run's ``frame``
    under the new name (the same pose, camera, bands and centre uncertainty: static rigs)."""
    images, bands = dict(model.images), dict(model.bands)
    centres, covariances = dict(model.centre_sigma_m), dict(model.centre_covariance_m2)
    reference = _frame_images(model, frame)
    stand_ins = dict(model.stand_ins)
    for name in names:
        if name not in images:
            ref = reference[ImageName.parse(name).camera]  # read_detections admitted only these cameras
            image = copy.copy(model.images[ref])
            image.name = name
            images[name], stand_ins[name] = image, ref
            if ref in centres:
                centres[name] = centres[ref]
            if ref in covariances:
                covariances[name] = covariances[ref]
    lent_frames = {ImageName.parse(name).frame for name in stand_ins}
    by_frame: dict[str, list[str]] = {}
    for name in images:
        if ImageName.parse(name).frame in lent_frames:
            by_frame.setdefault(ImageName.parse(name).frame, []).append(name)
    for group in by_frame.values():
        for a, b in itertools.permutations(group, 2):
            if a in model.stand_ins and b in model.stand_ins or a not in stand_ins and b not in stand_ins:
                continue  # the bands the model has (the run's, or an earlier lending's)
            # a view of the run's own frame beside a lent one (its narrow image missing there): the lending
            # frame's band between their cameras, as for two lent views
            ra, rb = (stand_ins.get(n) or reference.get(ImageName.parse(n).camera) for n in (a, b))
            band = model.bands.get((ra, rb)) if ra is not None and rb is not None else None
            if band is not None:
                bands[(a, b)] = band
    return dataclasses.replace(model, images=images, bands=bands, centre_sigma_m=centres,
                               centre_covariance_m2=covariances, stand_ins=stand_ins)


def _run_image_grey(model: RunModel, name: str) -> np.ndarray | None:
    """The narrow image the run was made from, as greys; None (and why, logged) where it is unreadable or its file
    now holds other pixels (a new recording under the same names must not lend its appearance to the run's)."""
    assert model.images_root is not None
    path = model.images_root / name
    if name in model.stand_ins and not path.is_file():
        return None  # a frame the run was not given: said once for all (associate)
    recorded = model.image_sha256.get(name)
    try:
        changed = recorded is not None and file_sha256(path) != recorded
    except OSError:
        changed = False  # read_grey below says it cannot be read
    said = name in model.images_said  # a frame is associated again (the timing check, frames paired by time)
    if changed:
        if not said:
            model.images_said.add(name)
            logger.warning("%s changed since the run (its content is not the one the run recorded), so its view is "
                           "associated by geometry only (no appearance); re-run `rigsfm run` on these images", path)
        return None
    grey = read_grey(path)
    if grey is None and not said:
        model.images_said.add(name)
        logger.warning("%s cannot be read, so its view is associated by geometry only (no appearance)", path)
    return grey


def require_floor(model: RunModel, out: Path) -> None:
    """Heights mean metres above the floor only in the floor frame."""
    frame = (model.world or {}).get("frame")
    if frame != "floor":
        raise InputError(f"'{out}' is not in the floor frame (world: {frame or 'unknown'}), so heights above the floor "
                         "are unknown: re-run `rigsfm run` with known lengths on the floor (scale.yaml) so it finds "
                         "the floor")


@dataclass
class FramePersons:
    frame: str
    result: FrameResult
    detections: Detections
    views: list[View]
    seconds: float = 0.0  # wall time of this frame's association
    cpu_seconds: float = 0.0  # this process's CPU time for it (the next frame's images, read meanwhile, included)
    poses_from: str | None = None  # the run's frame whose poses its views took (a frame the run was not given)
    # the views that took them: all of a frame the run was not given, some of one whose narrow images it lacked
    lent_views: tuple[str, ...] = ()
    track: np.ndarray | None = None  # per person, its track through the recording (rigsfm.associate.trajectories)
    links: Links | None = None  # its persons linked to the frame before's; None: the first frame


NO_BANDS = ("the run holds no epipolar band for any pair of {its} narrow images (its uncertainty was not computed), so "
            "the association sees the pixel noise only and misses persons wherever the poses are off: re-run `rigsfm "
            "run` until narrow_poses.json has epipolar_band_95_px")


def frame_views(model: RunModel, detections: Detections, frame: str, names: list[str],
                notes: FrameNotes | None = None) -> list[View]:
    """``notes``: where a frame without bands is noted, to be said once for all frames (else said here)."""
    views = [View.of(model.images[name], detections.images[name].xy) for name in sorted(names)]
    pairs = {key: band for key, band in model.bands.items() if key[0] in names and key[1] in names}
    if len(views) >= 2 and not pairs:
        if notes is None:
            logger.warning("%s: " + NO_BANDS.format(its="its"), frame)
        else:
            notes.no_bands.append(frame)
    sigmas = view_pose_sigmas([v.name for v in views], pairs)
    for view in views:
        view.radius_px = detections.images[view.name].radius
        view.sigma_pose_px = sigmas[view.name]
        view.centre_sigma_m = model.centre_sigma_m.get(view.name, 0.0)
        view.centre_covariance_m2 = model.centre_covariance_m2.get(view.name)
        if model.images_root is not None:
            view.grey = _run_image_grey(model, view.name)
    return views


def associate_frames(model: RunModel, detections: Detections, options: AssociateOptions,
                     progress: Callable[[int, int], None] | None = None,
                     frames: list[tuple[str, list[str]]] | None = None) -> list[FramePersons]:
    """The persons of every frame of ``detections`` (library entry; nothing written); ``progress(done, total)``
    after each frame; ``frames``: each frame's images, where not the frames of their names (rigs paired by time,
    rigsfm.associate.sync.paired_frames).

    A narrow camera's pose error is the same in every frame, so the shifts the crowd finds in one frame carry to the
    next frame's images of the same cameras (pooled with each frame's own groups); a frame whose cameras all carry
    one is associated once instead of self-calibrating from scratch."""
    if options.appearance:
        _say_lent_images_missing(model)
    out: list[FramePersons] = []
    carried: dict[str, View] = {}  # per camera (<rig>/narrow), its view in the latest frame
    frames = list(detections.frames().items()) if frames is None else frames
    notes = FrameNotes()
    if progress:  # the work starts: its bar from here
        progress(0, len(frames))
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="rigsfm-frame-views") as reader:
        # the next frame's images are read and decoded while this one is associated (OpenCV's decoder releases the
        # GIL; the association holds it)
        pending = reader.submit(frame_views, model, detections, *frames[0], notes) if frames else None
        for k, (frame, _) in enumerate(frames):
            views = pending.result()  # type: ignore[union-attr]  # one per frame
            pending = (reader.submit(frame_views, model, detections, *frames[k + 1], notes) if k + 1 < len(frames)
                       else None)
            lent_views = tuple(v.name for v in views if v.name in model.stand_ins)
            lent = {ImageName.parse(model.stand_ins[name]).frame for name in lent_views}
            out.append(_associate_frame(frame, views, detections, options, carried, out[-1] if out else None,
                                        min(lent) if lent else None, lent_views, notes))
            if progress:
                progress(len(out), len(frames))
    if options.revisit:
        _revisit(model, detections, options, carried, out, notes)
    notes.say()
    ids, links = tracks([(f.result.points, f.result.covariances) for f in out])
    for found, track, link in zip(out, ids, links):
        found.track, found.links = track, link
    return out


def _say_lent_images_missing(model: RunModel) -> None:
    """One warning (per command: ``model.images_said``) for the narrow images of frames the run was not given that
    are not beside its images: their views are associated by geometry only."""
    root = model.images_root
    missing = [n for n in model.stand_ins if (root is None or not (root / n).is_file()) and n not in model.images_said]
    if missing:
        model.images_said.update(missing)
        logger.warning("%d narrow image(s) of the frames the run was not given are not beside its images in %s (%s): "
                       "their views are associated by geometry only; put them there (<rig>/narrow/<frame file>) for "
                       "the heads' and torsos' greys", len(missing), root or "(unknown)",
                       quoted(missing[:3]) + (" ..." if len(missing) > 3 else ""))


def _revisit(model: RunModel, detections: Detections, options: AssociateOptions, carried: dict[str, View],
             out: list[FramePersons], notes: FrameNotes) -> None:
    """Associate again, carried, each frame whose own crowd corrected none of its views (its persons found on the run's
    poses) where a later frame's did for every one of its cameras: a static camera's shift is the same in every frame,
    and ``carried`` holds it as the recording's frames since refined it. Backwards, each frame looking for the persons
    of the frame after it."""
    for k in range(len(out) - 1, -1, -1):
        done = out[k]
        cameras = [ImageName.parse(v.name).camera for v in done.views]
        if any(v.band_sigma_px is not None for v in done.views) or not cameras \
                or not all(c in carried for c in cameras):
            continue
        names = [v.name for v in done.views]
        views = frame_views(model, detections, done.frame, names, notes)
        logger.info("%s: associated again with the shifts later frames found", done.frame)
        notes.forget(done.frame)
        after = out[k + 1] if k + 1 < len(out) else None
        # the recording's shifts, not this frame's refinement of them: the frames after it already hold those
        kept = dict(carried)
        out[k] = _associate_frame(done.frame, views, detections, options, kept, after, done.poses_from,
                                  done.lent_views, notes)
        out[k].seconds += done.seconds  # the frame's time: both its associations
        out[k].cpu_seconds += done.cpu_seconds


def _associate_frame(frame: str, views: list[View], detections: Detections, options: AssociateOptions,
                     carried: dict[str, View], before: FramePersons | None, poses_from: str | None,
                     lent_views: tuple[str, ...] = (), notes: FrameNotes | None = None) -> FramePersons:
    """One frame of :func:`associate_frames`; ``carried`` (per camera, its latest view) is updated; what it warns of
    goes into ``notes``."""
    cameras = [ImageName.parse(v.name).camera for v in views]
    known = bool(views) and all(c in carried for c in cameras)
    if known:
        for view, camera in zip(views, cameras):
            view.carry(carried[camera])
    wall, cpu = time.perf_counter(), time.process_time()
    result = associate_views(views, options, carried=known, earlier=before.result if before else None)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    logger.info("%s: %d persons in %.2f s (%.2f s CPU)", frame, len(result), wall, cpu)
    if notes is not None:
        notes.add(frame, result, options, carried=known)
    carried.update((camera, view) for camera, view in zip(cameras, views) if view.band_sigma_px is not None)
    for view in views:
        view.grey = None  # read for this frame's appearance only; kept, a recording would hold every image
    return FramePersons(frame, result, detections, views, wall, cpu, poses_from, lent_views)


FEW_CONFIDENT_SHARE = 0.1  # below it, a frame's persons are mostly chance (benchmarks/README.md, *confidence*)
SHOWN_FRAMES = 5  # frames named in a warning said once for all of them


@dataclass
class FrameNotes:
    """What a command's frames warn of, said once a kind with the frames named (:meth:`say`): per frame, a CSV of
    hundreds would bury the terminal under one warning repeated."""

    few_confident: list[tuple[str, int, int]] = field(default_factory=list)  # (frame, confident persons, persons)
    two_views: list[tuple[str, int]] = field(default_factory=list)  # (frame, persons)
    no_bands: list[str] = field(default_factory=list)  # frames whose views have no band between them

    def add(self, frame: str, result: FrameResult, options: AssociateOptions, carried: bool = False) -> None:
        """Note where few of a frame's persons are the kind the views' corrections rest on (three or more views, a
        positive score; not for a frame whose views carry an earlier frame's corrections): there the views keep the
        run's pose errors and chance groupings of different persons dominate, whatever each person's confidence
        says. A frame of two views has none of that kind: it is noted as such, whatever its persons."""
        if len(result.views) == 2:  # with or without persons: the frame cannot confirm one
            self.two_views.append((frame, len(result)))
            return
        if not len(result):
            return
        confident = len(_confident(result.members, result.scores, options))
        # a share, not a count, so that a small crowd every view sees clearly does not warn
        if not carried and len(result.views) >= 3 and confident < FEW_CONFIDENT_SHARE * len(result):
            self.few_confident.append((frame, confident, len(result)))

    def forget(self, frame: str) -> None:
        """Drop what ``frame`` noted (it is associated again)."""
        self.few_confident = [n for n in self.few_confident if n[0] != frame]
        self.two_views = [n for n in self.two_views if n[0] != frame]
        self.no_bands = [f for f in self.no_bands if f != frame]

    def say(self) -> None:
        if self.no_bands:
            logger.warning("%s: " + NO_BANDS.format(its="their" if len(self.no_bands) > 1 else "its"),
                           _named([(f, "") for f in self.no_bands]))
        if len(self.few_confident) == 1:
            (frame, confident, persons), = self.few_confident
            head = f"{frame}: only {confident} of its {persons} persons are"
        else:
            head = _named([(f, f"{c} of {n} persons") for f, c, n in self.few_confident]) + ": only those are"
        if self.few_confident:
            logger.warning("%s seen by three or more views with a positive score, too few to correct the views' pose "
                           "errors from the crowd: most of the persons may be chance groupings of different persons, "
                           "whatever their confidence (the model's odds, not a measured rate). More narrow views "
                           "sharing the crowd, or a calibration with narrower bands, is what helps", head)
        if self.two_views:
            logger.warning("%s: two narrow views only, so no person there is confirmed by a third: each is a pair of "
                           "detections on each other's epipolar band, which two different persons on one band make as "
                           "well, and the views' pose errors are not corrected from the crowd; any person may be a "
                           "chance pairing, whatever its confidence. A third narrow view sharing the crowd is what "
                           "confirms them", _named([(f, f"{n} persons") for f, n in self.two_views]))


def _named(frames: list[tuple[str, str]]) -> str:
    """``frame`` alone, or 'N frames (a: what, b: what, ...)' with ``SHOWN_FRAMES`` of them."""
    if len(frames) == 1 and not frames[0][1]:
        return frames[0][0]
    shown = ", ".join(f"{f}: {what}" if what else f for f, what in frames[:SHOWN_FRAMES])
    more = ", ..." if len(frames) > SHOWN_FRAMES else ""
    return f"{frames[0][0]} ({frames[0][1]})" if len(frames) == 1 else f"{len(frames)} frames ({shown}{more})"


def refuse_workspace_files(dest: Path, workspace: Workspace) -> None:
    """--out may not be the workspace, a folder that holds it, or one of the folders its other commands write
    (their files are rigsfm's, so 'files rigsfm did not write' would be the wrong reason to give)."""
    if workspace.is_within(dest):
        raise InputError(f"--out '{dest}' is the workspace or a folder that holds it; choose a folder of its own "
                         f"(the default is {workspace.associate})")
    resolved = Path(dest).resolve()
    for owned, command in ((workspace.sparse, "run"), (workspace.mapping, "run"), (workspace.track.root, "track"),
                           (workspace.exports, "export")):
        if resolved.is_relative_to(owned.resolve()):
            raise InputError(f"--out '{dest}' is inside the workspace's own {owned.name}/ folder (rigsfm {command}'s); "
                             f"choose {workspace.associate} (the default) or a folder of its own")


def lent_after_moves(workspace: Workspace, lent: Iterable[str], fingerprint: str | None = None) -> str | None:
    """A warning where ``rigsfm track`` (OUT/track, against this model) found a rig moved and views of it at or after
    its step take lent poses (``lent``: narrow image names): the run's pose no longer holds there. ``fingerprint``:
    OUT/sparse's ``model_fingerprint`` where the caller has it."""
    from rigsfm.track.pipeline import moved_steps

    try:
        poses = json.loads(workspace.track.poses_json.read_text(encoding="utf-8"))
        if fingerprint is None:
            fingerprint = model_fingerprint(workspace.sparse)
        if poses["reference"]["fingerprint"] != fingerprint:
            return None  # a series of an earlier model: its verdicts say nothing of this one (report.html says so)
        steps = moved_steps(poses)
    except (OSError, ValueError, KeyError, TypeError, AttributeError, IndexError):
        return None
    after: dict[str, list[str]] = {}
    for name in sorted(lent):
        parsed = ImageName.parse(name)
        if parsed.rig in steps and parsed.frame >= steps[parsed.rig]["frame"]:  # track orders frames by file name
            after.setdefault(parsed.rig, []).append(parsed.frame)
    if not after:
        return None
    named = "; ".join(f"{rig}: {len(frames)} frame(s) from {frames[0]}, its step at {steps[rig]['frame']}"
                      for rig, frames in after.items())
    return (f"LENT AFTER A MOVE: `rigsfm track` found {', '.join(after)} moved ({workspace.track.poses_json}), and "
            f"its views from its step on take the poses of --poses-from ({named}): those views' persons are "
            "unreliable; calibrate the frames since with `rigsfm run` and associate them against that result")


def associate(out: Path, detections_csv: Path, options: AssociateOptions | None = None,
              progress: Callable[[int, int], None] | None = None) -> Path:
    """Read OUT (a finished run) and DETECTIONS, associate every frame, write DIR (default OUT/associate);
    ``progress(done, total)`` after each frame."""
    options = options or AssociateOptions()
    workspace = Workspace(Path(out))
    dest = Path(options.out) if options.out is not None else workspace.associate
    refuse_workspace_files(dest, workspace)
    workspace.require_result()  # before the lock, which makes the folder
    with workspace.reading():  # the persons of one model: a run rewriting it now is refused
        return _associate(workspace, dest, Path(detections_csv), options, progress)


def _associate(workspace: Workspace, dest: Path, detections_csv: Path, options: AssociateOptions,
               progress: Callable[[int, int], None] | None) -> Path:
    from rigsfm.associate.output import check_destination, refuse_edited, write_results
    from rigsfm.associate.sync import (
        check_frame_offsets,
        given_offsets,
        paired_frames,
        recording_frames,
        with_camera_bands,
    )

    out = workspace.root
    fingerprint = model_fingerprint(workspace.sparse)  # the persons' model: the track series' and the manifest's
    previous = check_destination(dest, options.overwrite)
    model = load_run(Path(out))
    # a model's images have cameras
    sizes = {name: (image.camera.width, image.camera.height)  # type: ignore[union-attr]
             for name, image in model.images.items()}
    stand_in = frame_sizes(model, options.poses_from) if options.poses_from is not None else None
    detections = read_detections(Path(detections_csv), sizes, model.known, stand_in, options.poses_from)
    if options.poses_from is not None:
        model = with_stand_ins(model, detections.images, options.poses_from)
        moved = lent_after_moves(workspace, model.stand_ins, fingerprint)
        if moved:
            logger.warning("%s", moved)
    require_floor(model, Path(out))
    refuse_edited(dest, previous, detections.frames())
    asked = options.frame_offsets
    # a file's offsets are checked before any association (rigsfm run's file and rules)
    applied = {} if asked in (None, "off", "auto") else given_offsets(
        Path(asked), detections, (ImageName.parse(n).rig for n in model.images))
    paired = None
    recording = recording_frames(detections, model.images_root, model.known)  # offsets count its frames
    if applied:
        paired = paired_frames(detections, applied, recording)
        model = with_camera_bands(model, [names for _, names in paired])
    if paired:
        _say_left_out(detections, paired)
    frames = associate_frames(model, detections, options, progress, paired)
    check = None
    if asked != "off":
        check = check_frame_offsets(model, detections, frames, options, str(asked or "check"), applied, recording)
        if asked == "auto" and check.named:
            paired = paired_frames(detections, check.named, recording)
            model = with_camera_bands(model, [names for _, names in paired])
            _say_left_out(detections, paired)
            frames = associate_frames(model, detections, options, progress, paired)
            check.applied = dict(check.named)
        if check.warning:
            logger.warning("%s", check.warning)
    return write_results(dest, model, frames, options, previous, fingerprint,
                         None if check is None else check.to_dict())


def _say_left_out(detections: Detections, paired: list[tuple[str, list[str]]]) -> None:
    """One warning for the images that frames paired by time leave out (taken at an instant of a frame the
    DETECTIONS do not hold, or outside the recording): their detections are in no frame's persons."""
    kept = {name for _, names in paired for name in names}
    left = sorted(set(detections.images) - kept)
    if left:
        logger.warning("%d narrow image(s) of the detections were taken, by the frame offsets, at frames the "
                       "detections do not hold (%s%s: past the recording's ends, or frames left out of the "
                       "detections): their detections are left out; where those frames were recorded, give their "
                       "detections to pair them", len(left), quoted(left[:3]), " ..." if len(left) > 3 else "")
