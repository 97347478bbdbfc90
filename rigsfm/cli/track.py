"""``rigsfm track``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from rigsfm.cli.common import configure_logging, console, fail_cleanly, flag, progress_bars
from rigsfm.track.options import Executor, Thresholds, TrackOptions


@fail_cleanly
def track_command(
    out: Annotated[Path, typer.Argument(metavar="OUT", help="workspace of `rigsfm run` (sparse/, database.db)", show_default=False)],
    new_images: Annotated[Path, typer.Argument(metavar="NEW_IMAGES", help="NEW_IMAGES/<rig>/<wide|narrow>/<frame file>, many frames",
                                               show_default=False)],
    executor: Annotated[Executor, typer.Option("--executor", help="local (process pool) or ray")] = Executor.LOCAL,
    address: Annotated[str | None, typer.Option(
        "--address", metavar="ADDRESS", help="Ray cluster address, e.g. auto or ray://HEAD:10001 (with --executor ray)  [default: start "
                          "a local Ray instance]", show_default=False)] = None,
    workers: Annotated[int, typer.Option("--workers", min=1, metavar="N", help="processes (local) / CPUs of a local Ray "
                                                                         f"instance  [default: all cores, {os.cpu_count() or 1}]", show_default=False)] =
    max(1, os.cpu_count() or 1),
    rotation_threshold_deg: Annotated[float, typer.Option("--rotation-threshold-deg", min=0.0, metavar="DEG",
                                                          help="flag a rotation change above this")] = 0.05,
    translation_threshold_mm: Annotated[float, typer.Option("--translation-threshold-mm", min=0.0, metavar="MM",
                                                            help="flag a centre shift above this")] = 5.0,
    overwrite: Annotated[bool, flag("--overwrite", help="discard earlier results and register every frame again "
                                                        "(required after `rigsfm run --overwrite`)")] = False,
    verbose: Annotated[bool, flag("--verbose", "-v", help="show rigsfm's log (info level) on the terminal")] = False,
) -> None:
    """Re-estimate every rig's pose in every new frame; flag shake and moved rigs (OUT/track/)."""
    configure_logging(verbose)
    from rigsfm.track.pipeline import track

    options = TrackOptions(executor=executor, address=address, workers=workers, overwrite=overwrite,
                           thresholds=Thresholds(rotation_deg=rotation_threshold_deg,
                                                 translation_mm=translation_threshold_mm))
    with progress_bars() as progress:
        task = progress.add_task("track", total=None)
        result = track(out, new_images, options,
                       progress=lambda done, total: progress.update(task, completed=done, total=total))
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
