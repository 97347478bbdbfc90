"""``rigsfm track OUT NEW_IMAGES``: re-register every rig in every new frame against the reference in OUT.

Outputs (OUT/track/): ``poses.json`` (per rig: baseline, verdict, frames), ``poses.csv`` (one row per
frame), ``plots/<rig>.png``; COLMAP's log and a line per frame are appended to OUT/colmap.log. Frames already in poses.json (same rig and frame file name, same content) are
skipped, so the command can run again as recordings arrive; results are merged, checkpointed every
``checkpoint_every`` frames and written atomically. Each tracked frame records its files' fingerprints (size,
modification time, SHA-256): a file that reuses a tracked name with other content (a new recording that numbers
its frames from 0 again) is refused, naming it, before anything is registered: its earlier result would be lost
(``--overwrite`` starts the series anew); a frame that gained an image (its narrow one) is registered again. Flags and verdicts are recomputed over the whole
series on every run (with the thresholds of that run).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from rigsfm.core import charts
from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.executors import check_reachable
from rigsfm.core.io import file_sha256, write_bytes_atomic, write_json_atomic, write_text_atomic
from rigsfm.core.rig import RigCalibration, nfc
from rigsfm.core.workspace import TrackPaths, Workspace, colmap_log_to
from rigsfm.run.inputs.images import (
    check_image_folder,
    check_stored_size,
    rig_folders,
    rigs_missing_frames,
    scan_images,
)
from rigsfm.track.executors import run_frames
from rigsfm.track.options import TrackOptions
from rigsfm.track.plot import plot_rig
from rigsfm.track.reference import ReferenceMap, load_reference
from rigsfm.track.register import FrameTask
from rigsfm.track.results import assemble, derive, load_poses, to_csv

logger = logging.getLogger(__name__)


@dataclass
class TrackResult:
    paths: TrackPaths
    poses: dict  # poses.json content
    processed: int  # frames registered (or attempted) in this run
    skipped: int  # frames already in poses.json


def frame_tasks(new_images: Path, reference: ReferenceMap) -> list[FrameTask]:
    """One task per (rig, frame) under NEW_IMAGES/<rig>/<wide|narrow>/<frame file>."""
    new_images = check_image_folder(new_images)
    by_nfc = {nfc(name): name for name in reference.rigs}  # folders match rigs Unicode-normalised
    folders = rig_folders(new_images)
    unknown = sorted(path.name for key, path in folders.items() if key not in by_nfc)
    present = sorted(by_nfc[key] for key in folders if key in by_nfc)
    if unknown:
        raise InputError(f"{new_images}: folder(s) {', '.join(unknown)} are not rigs of the reference model "
                         f"{reference.sparse}; move them out or track them against their own reference")
    if not present:
        raise InputError(f"{new_images} has no <rig>/wide/ folders with images")
    # scan_images checks the layout; the sizes from the files' headers (the pixels are the workers' to read)
    rigs = []
    for name in present:
        rig = reference.rigs[name]
        narrow = rig.wide if rig.narrow is None else rig.narrow
        narrow_from_wide = pycolmap.Rigid3d() if rig.narrow_from_wide is None else rig.narrow_from_wide
        rigs.append(RigCalibration(name, rig.wide, narrow, narrow_from_wide))
    images: dict[tuple[str, str], dict[str, Path | bytes]] = {}
    entries = scan_images(new_images, rigs, check_pixels=False)
    cameras = {rig.name: rig for rig in rigs}
    for entry in entries:
        check_stored_size(entry, cameras[entry.rig].camera(entry.sensor))
    missing = rigs_missing_frames(entries, rigs)
    if missing is not None:  # as `rigsfm run` warns: a misnamed or lost file otherwise only shortens a rig's series
        logger.warning("MISSING FRAMES: %s", missing)
    for entry in entries:
        images.setdefault((entry.rig, entry.frame), {})[entry.sensor] = entry.path
    return [FrameTask(rig, frame, sensors) for (rig, frame), sensors in sorted(images.items())]


def fingerprint(path: Path, known: dict | None = None) -> dict:
    """Size, modification time (ns) and SHA-256 of a file; the hash of ``known`` is reused when size and time
    match it (no re-reading of unchanged files)."""
    stat = Path(path).stat()
    if known and known.get("size") == stat.st_size and known.get("mtime_ns") == stat.st_mtime_ns:
        return dict(known)
    return {"size": stat.st_size, "mtime_ns": stat.st_mtime_ns, "sha256": file_sha256(path)}


def task_fingerprints(task: FrameTask, known: dict | None = None) -> dict:
    return {sensor: fingerprint(path, (known or {}).get(sensor)) for sensor, path in sorted(task.images.items())
            if isinstance(path, (str, os.PathLike))}


def compare_with_tracked(task: FrameTask, entry: dict) -> tuple[list[str], list[str]]:
    """(sensors whose image differs from the one ``entry`` was tracked from, sensors with an image ``entry`` was
    tracked without); entries written before fingerprints were recorded count as unchanged."""
    known = entry.get("files")
    if not isinstance(known, dict) or not known:
        return [], []
    now = {sensor: f["sha256"] for sensor, f in task_fingerprints(task, known).items()}
    before = {sensor: (f or {}).get("sha256") for sensor, f in known.items()}
    return ([sensor for sensor in sorted(now) if sensor in before and now[sensor] != before[sensor]],
            [sensor for sensor in sorted(now) if sensor not in before])


def tracked_again(tasks: list[FrameTask], frames: dict, poses_json: Path) -> list[FrameTask]:
    """The tracked frames to register again: those that gained an image (a narrow one added since) from the same
    recording. Refuses frames whose names are tracked already from other images (a new recording numbered from 0
    again, another scene's images): registering them would replace the earlier results, which nothing else keeps."""
    replaced, grown = [], []
    for task in tasks:
        if (task.rig, task.frame) in frames:
            differ, added = compare_with_tracked(task, frames[(task.rig, task.frame)])
            if differ:
                replaced.append(f"'{task.rig}/{task.frame}'")
            elif added:
                grown.append(task)
    if replaced:
        raise WorkspaceError(
            f"'{poses_json}' holds results of {len(replaced)} frame(s) of the same name tracked from other images "
            f"({', '.join(replaced[:3])}{', ...' if len(replaced) > 3 else ''}; a new recording that reuses their file "
            "names?): name the new frames so that they differ from the tracked ones (e.g. by a timestamp) to add "
            "them to the series, or pass --overwrite to start the series anew (the earlier results are discarded); "
            "nothing was registered or changed")
    if grown:
        logger.info("%d tracked frame(s) have images they were tracked without: registered again", len(grown))
    return grown


def _save(paths: TrackPaths, poses: dict, plots: bool, rigs: Iterable[str] = ()) -> None:
    """Write poses.json and poses.csv, and with ``plots`` each rig's plot; the plots of ``rigs`` (the reference's)
    that the series no longer holds (an --overwrite's new series without them) are removed, not left to show the
    discarded series."""
    write_json_atomic(paths.poses_json, poses)
    write_text_atomic(paths.poses_csv, to_csv(poses))
    if plots:
        for name, rig in poses["rigs"].items():
            plot = plot_rig(name, {**rig, "thresholds": poses["thresholds"]})
            write_bytes_atomic(paths.plot(name), charts.encode(plot))
        for name in set(rigs) - set(poses["rigs"]):
            paths.plot(name).unlink(missing_ok=True)  # rigsfm's name for the rig's plot


def warn_not_metric(workspace: Workspace) -> None:
    """Warn where OUT's result has no scale: a rig's shift and --translation-threshold-mm then are thousandths of
    its arbitrary unit, which the table and poses.json call millimetres."""
    from rigsfm.core.summary import Summary

    summary = Summary.read(workspace.summary)
    if summary is not None and summary.metric is False:
        logger.warning("NOT METRIC: %s has no scale: each shift called 'mm', and --translation-threshold-mm, are "
                       "thousandths of its arbitrary unit; give `rigsfm run` a scale.yaml for millimetres",
                       workspace.root)


def moved_steps(poses: dict) -> dict[str, dict]:
    """The rigs of a poses.json (``poses``) whose verdict is 'moved', each with its first step."""
    return {name: rig["verdict"]["steps"][0] for name, rig in poses["rigs"].items()
            if rig["verdict"]["verdict"] == "moved" and rig["verdict"]["steps"]}


def moved_warning(poses: dict, out: str) -> str | None:
    """One warning naming the rigs whose verdict is 'moved', each with its first step, and what no longer holds:
    the run's poses of that rig, so its pairs' F_ji and bands, the exports and `associate --poses-from`."""
    moved = list(moved_steps(poses).items())
    if not moved:
        return None
    steps = "; ".join(f"{name} at {step['frame']} ({step['rotation_deg']:.3f} deg, {step['translation_mm']:.1f} mm)"
                      for name, step in moved)
    return (f"MOVED: {steps}. The poses of {out} (narrow_poses.json: their pairs' F_ji and bands; the exports; "
            "`rigsfm associate --poses-from`) no longer hold for its images from that frame on: calibrate the network "
            "again on frames taken since (`rigsfm run IMAGES --rigs rigs.yaml --out NEW_OUT`, IMAGES holding those "
            "frames of every rig)")


def track(out: Path, new_images: Path, options: TrackOptions | None = None, *,
          progress: Callable[[int, int], None] | None = None) -> TrackResult:
    """Register the new frames, merge them into OUT/track and return the merged result."""
    options = options or TrackOptions()
    thresholds = options.thresholds
    if thresholds.rotation_deg <= 0 or thresholds.translation_mm <= 0:
        raise InputError("the rotation and translation thresholds must be positive")
    if options.executor == "ray" and options.address:  # before the reference is read: fail in seconds, not minutes
        check_reachable(options.address)
    workspace = Workspace(Path(out))
    workspace.require_result()
    root, given = workspace.root.resolve(), Path(new_images).resolve()
    if root == given or (root.parent == given and not root.name.startswith(".")):  # (before the reference is read)
        where = "is the workspace OUT, whose folders are not rigs" if root == given else \
            f"holds the workspace OUT '{out}', which is not a rig"
        raise InputError(f"NEW_IMAGES '{new_images}' {where}: give the folder of the new recording "
                         "(<rig>/<wide|narrow>/<frame file>)")
    warn_not_metric(workspace)
    paths = workspace.track
    reference = load_reference(workspace.root, options=options.registration)
    tasks = frame_tasks(new_images, reference)
    with workspace.lock():
        frames = {} if options.overwrite else load_poses(paths.poses_json, reference)
        again = tracked_again(tasks, frames, paths.poses_json)
        todo = [t for t in tasks if (t.rig, t.frame) not in frames or t in again]
        logger.info("%d new frames to register, %d already tracked", len(todo), len(tasks) - len(todo))
        files = {(t.rig, t.frame): task_fingerprints(t) for t in todo}
        bad: list[str] = []
        failed: list[str] = []
        done: list = [0, time.monotonic()]

        def on_result(record: dict) -> None:
            # kept before it is announced: a Ctrl-C between the two must not lose a frame the log calls registered
            if record["status"] == "bad_input":
                bad.append(record["reason"])
            else:
                if record["status"] != "registered":
                    failed.append(f"{record['rig']}/{record['frame']}: {record.get('reason') or record['status']}")
                key = (record["rig"], record["frame"])
                frames[key] = {**derive(record, reference.rigs[record["rig"]]), "files": files[key]}
            done[0] += 1
            logger.info("Frame %s/%s: %s (%d of %d)", record["rig"], record["frame"], record["status"], done[0],
                        len(todo))
            if done[0] % options.checkpoint_every == 0:
                _save(paths, assemble(frames, reference, thresholds), plots=False)
            if progress:
                progress(done[0], len(todo))

        if progress:  # the work starts: its bar from here
            progress(0, len(todo))
        try:
            with colmap_log_to(workspace.colmap_log):  # glog's lines (every extractor's start) are not the user's
                run_frames(todo, reference, on_result, executor=str(options.executor), workers=options.workers,
                           address=options.address, options=options.registration)
        finally:
            poses = assemble(frames, reference, thresholds)
            if frames or options.overwrite:
                _save(paths, poses, plots=True, rigs=reference.rigs)
    if failed:  # else a scene's wrong images, none registered, left only the verdict table, all 'stable'
        logger.warning("FRAMES NOT REGISTERED: %d of %d new frame(s) did not register against the reference (%s%s); "
                       "they are in poses.csv without a pose%s", len(failed), len(todo), "; ".join(failed[:2]),
                       "; ..." if len(failed) > 2 else "",
                       f"; none did: are these images of the scene of '{workspace.root}'?" if len(failed) == len(todo)
                       else "")
    unsettled = {rig: record["verdict"]["unsettled_frames"] for rig, record in poses["rigs"].items()
                 if record["verdict"].get("unsettled_frames")}
    if unsettled:
        logger.warning("POSSIBLY MOVED: %s off in the last frame(s) after still ones (%s), too few yet to call a step "
                       "(%d frames after it): a rig moved just now reads 'shaking' until then. Check it, or track the "
                       "next frames", ", ".join(unsettled), ", ".join(f"{rig}: {k}" for rig, k in unsettled.items()),
                       thresholds.min_persist_frames)
    moved = moved_warning(poses, workspace.shell_root)
    if moved:
        logger.warning("%s", moved)
    if bad:
        raise InputError(f"{len(bad)} frame(s) could not be used (the others are saved): {bad[0]}"
                         + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""))
    return TrackResult(paths, poses, len(todo), len(tasks) - len(todo))
