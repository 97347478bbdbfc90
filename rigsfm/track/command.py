"""``rigsfm track OUT NEW_IMAGES``: re-register every rig in every new frame against the reference in OUT.

Outputs (OUT/track/): ``poses.json`` (per rig: baseline, verdict, frames), ``poses.csv`` (one row per
frame), ``plots/<rig>.png``. Frames already in poses.json (same rig and frame file name) are skipped, so
the command can run again as recordings arrive; results are merged, checkpointed every
``checkpoint_every`` frames and written atomically. Flags and verdicts are recomputed over the whole
series on every run (with the thresholds of that run).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.run.inputs import scan_images
from rigsfm.core.io import write_json_atomic, write_text_atomic
from rigsfm.core.rig import RigCalibration
from rigsfm.track.verdict import Thresholds
from rigsfm.track.executors import run_frames
from rigsfm.track.plot import encode_png, plot_rig
from rigsfm.track.pose import RegistrationOptions
from rigsfm.track.reference import ReferenceMap, camera_from_spec, load_reference, rigid3d_from_matrix
from rigsfm.track.register import FrameTask
from rigsfm.track.results import assemble, derive, load_poses, to_csv

logger = logging.getLogger(__name__)


class Executor(str, Enum):
    LOCAL = "local"
    RAY = "ray"


@dataclass(frozen=True)
class TrackPaths:
    root: Path

    @property
    def poses_json(self) -> Path:
        return self.root / "poses.json"

    @property
    def poses_csv(self) -> Path:
        return self.root / "poses.csv"

    @property
    def plots(self) -> Path:
        return self.root / "plots"


@dataclass
class TrackResult:
    paths: TrackPaths
    poses: dict  # poses.json content
    processed: int  # frames registered (or attempted) in this run
    skipped: int  # frames already in poses.json


def frame_tasks(new_images: Path, reference: ReferenceMap) -> list[FrameTask]:
    """One task per (rig, frame) under NEW_IMAGES/<rig>/<wide|narrow>/<frame file>."""
    new_images = Path(new_images)
    if not new_images.is_dir():
        raise InputError(f"image folder {new_images} does not exist")
    present = sorted(p.name for p in new_images.iterdir() if p.is_dir() and not p.name.startswith("."))
    unknown = [name for name in present if name not in reference.rigs]
    if unknown:
        raise InputError(f"{new_images}: folder(s) {', '.join(unknown)} are not rigs of the reference model "
                         f"{reference.sparse}; move them out or track them against their own reference")
    if not present:
        raise InputError(f"{new_images} has no <rig>/wide/ folders with images")
    # scan_images checks the layout; pixel sizes are checked by the workers, which read the images anyway.
    rigs = [RigCalibration(name, camera_from_spec(reference.rigs[name].wide),
                           camera_from_spec(reference.rigs[name].narrow or reference.rigs[name].wide),
                           rigid3d_from_matrix(reference.rigs[name].narrow_from_wide
                                               if reference.rigs[name].narrow_from_wide is not None
                                               else [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]))
            for name in present]
    images: dict[tuple[str, str], dict[str, Path]] = {}
    for entry in scan_images(new_images, rigs, check_pixels=False):
        images.setdefault((entry.rig, entry.frame), {})[entry.sensor] = entry.path
    return [FrameTask(rig, frame, sensors) for (rig, frame), sensors in sorted(images.items())]


def write_bytes_atomic(path: Path, data: bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextlib.contextmanager
def _exclusive(root: Path) -> Iterator[None]:
    root.mkdir(parents=True, exist_ok=True)
    with open(root / ".lock", "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            raise WorkspaceError(f"another `rigsfm track` is writing {root}; wait for it to finish") from e
        yield


def _save(paths: TrackPaths, poses: dict, plots: bool) -> None:
    write_json_atomic(paths.poses_json, poses)
    write_text_atomic(paths.poses_csv, to_csv(poses))
    if plots:
        for name, rig in poses["rigs"].items():
            write_bytes_atomic(paths.plots / f"{name}.png", encode_png(plot_rig(name, {**rig, "thresholds": poses["thresholds"]})))


def track(out: Path, new_images: Path, *, executor: str = "local", address: str | None = None, workers: int = 2,
          thresholds: Thresholds | None = None, options: RegistrationOptions | None = None,
          overwrite: bool = False, checkpoint_every: int = 50,
          progress: Callable[[int, int], None] | None = None) -> TrackResult:
    """Register the new frames, merge them into OUT/track and return the merged result."""
    thresholds = thresholds or Thresholds()
    if thresholds.rotation_deg <= 0 or thresholds.translation_mm <= 0:
        raise InputError("the rotation and translation thresholds must be positive")
    options = options or RegistrationOptions()
    paths = TrackPaths(Path(out) / "track")
    reference = load_reference(Path(out), options=options)
    tasks = frame_tasks(new_images, reference)
    with _exclusive(paths.root):
        frames = {} if overwrite else load_poses(paths.poses_json, reference)
        todo = [t for t in tasks if (t.rig, t.frame) not in frames]
        logger.info("%d new frames to register, %d already tracked", len(todo), len(tasks) - len(todo))
        bad: list[str] = []
        done = [0, time.monotonic()]

        def on_result(record: dict) -> None:
            done[0] += 1
            if record["status"] == "bad_input":
                bad.append(record["reason"])
            else:
                frames[(record["rig"], record["frame"])] = derive(record, reference.rigs[record["rig"]])
            if done[0] % checkpoint_every == 0:
                _save(paths, assemble(frames, reference, thresholds), plots=False)
            if progress:
                progress(done[0], len(todo))

        try:
            run_frames(todo, reference, on_result, executor=executor, workers=workers, address=address,
                       options=options)
        finally:
            poses = assemble(frames, reference, thresholds)
            if frames or overwrite:
                _save(paths, poses, plots=True)
    if bad:
        raise InputError(f"{len(bad)} frame(s) could not be used (the others are saved): {bad[0]}"
                         + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""))
    return TrackResult(paths, poses, len(todo), len(tasks) - len(todo))


def track_command(
    out: Annotated[Path, typer.Argument(help="workspace of `rigsfm run` (sparse/, database.db)")],
    new_images: Annotated[Path, typer.Argument(help="NEW_IMAGES/<rig>/<wide|narrow>/<frame file>, many frames")],
    executor: Annotated[Executor, typer.Option("--executor", help="local (process pool) or ray")] = Executor.LOCAL,
    address: Annotated[Optional[str], typer.Option("--address", help="Ray cluster address (with --executor ray)")] = None,
    workers: Annotated[int, typer.Option("--workers", help="processes (local) / CPUs of a local Ray")] = max(1, os.cpu_count() or 1),
    rotation_threshold_deg: Annotated[float, typer.Option("--rotation-threshold-deg")] = 0.05,
    translation_threshold_mm: Annotated[float, typer.Option("--translation-threshold-mm")] = 5.0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="discard earlier results; re-register all")] = False,
) -> None:
    """Re-estimate every rig's pose in every new frame; flag shake and moved rigs (OUT/track/)."""
    from rich.console import Console
    from rich.table import Table

    console = Console()
    thresholds = Thresholds(rotation_deg=rotation_threshold_deg, translation_mm=translation_threshold_mm)
    result = track(out, new_images, executor=Executor(executor).value, address=address, workers=workers, thresholds=thresholds,
                   overwrite=overwrite)
    table = Table(title=f"rigsfm track: {result.processed} new frames, {result.skipped} already tracked")
    for column in ("rig", "verdict", "frames", "flagged", "steps (frame: deg, mm)", "jitter RMS (deg, mm)"):
        table.add_column(column)
    for name, rig in result.poses["rigs"].items():
        v = rig["verdict"]
        steps = "; ".join(f"{s['frame']}: {s['rotation_deg']:.3f}, {s['translation_mm']:.1f}" for s in v["steps"])
        jitter = "-" if v["jitter_rotation_deg"] is None else f"{v['jitter_rotation_deg']:.4f}, {v['jitter_translation_mm']:.1f}"
        table.add_row(name, v["verdict"], str(len(rig["frames"])), str(v["flagged_frames"]), steps or "-", jitter)
    console.print(table)
    console.print(f"results: {result.paths.poses_json}, {result.paths.poses_csv}, {result.paths.plots}/")
