"""``rigsfm associate``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rigsfm.cli.common import configure_logging, console, fail_cleanly, flag, progress_bars
from rigsfm.core.errors import InputError
from rigsfm.core.workspace import Workspace


@fail_cleanly
def associate_command(
    out: Annotated[Path, typer.Argument(metavar="OUT", help="workspace of a finished `rigsfm run`", show_default=False)],
    detections: Annotated[Path, typer.Argument(
        metavar="DETECTIONS", help="CSV image,x,y[,score][,label][,radius]: points in narrow images (COLMAP pixels), one or many "
        "synchronised frames; radius: the head's apparent radius (px), evidence of its depth",
        show_default=False)],
    dest: Annotated[Path | None, typer.Option("--out", metavar="DIR", help="folder to write [default: OUT/associate]",
                                                 show_default=False)] = None,
    heights: Annotated[str, typer.Option("--heights", metavar="LOW-HIGH",
                                         help="the points' heights above the floor (m)")] = "1.0-2.1",
    pixel_sigma: Annotated[float, typer.Option("--pixel-sigma", min=0.01, metavar="PX", help="detection noise per coordinate (px)")]
    = 2.0,
    detection_probability: Annotated[float | None, typer.Option(
        "--detection-probability", min=0.01, max=0.99, metavar="P", help="a person is detected in a view that sees it (occlusion "
                                                            "included) [default: estimated from each frame's persons]",
        show_default=False)] = None,
    size_noise: Annotated[float, typer.Option(
        "--size-noise", min=0.001, max=2.0, metavar="REL",
        help="the detector's relative error of a DETECTIONS radius (0.1: 10 %); used only where a frame's detections "
             "give radii")] = 0.1,
    self_calibration_rounds: Annotated[int, typer.Option(
        "--self-calibration-rounds", min=0, metavar="N",
        help="correct each view's pose error from the crowd, re-associating up to this many times (0: the run's poses)")] = 4,
    walk: Annotated[float, typer.Option(
        "--walk", min=0.0, max=10.0, metavar="M",
        help="how far a person walks per floor axis between two frames (1 sigma, m): a later frame looks for each "
             "person of the frame before within it first, and searches every pair only among the detections they "
             "leave (0: every pair in every frame)")] = 0.15,
    no_appearance: Annotated[bool, flag("--no-appearance", help="geometry only: leave out the heads' and torsos' greys "
                                        "sampled from the run's narrow images")] = False,
    overwrite: Annotated[bool, flag("--overwrite", help="replace an earlier association in --out")] = False,
    verbose: Annotated[bool, flag("--verbose", "-v", help="show rigsfm's log (info level) on the terminal")] = False,
) -> None:
    """Find the same person across narrow views: group detections into 3D persons per frame (persons.csv/json, a
    floor map with 95 % ellipses, a density grid)."""
    configure_logging(verbose)
    from rigsfm.associate import AssociateOptions, associate
    from rigsfm.core.ground import parse_heights

    try:
        options = AssociateOptions(heights=parse_heights(heights), pixel_sigma=pixel_sigma,
                                   detection_probability=detection_probability, size_noise=size_noise,
                                   self_calibration_rounds=self_calibration_rounds, walk_m=walk or None,
                                   appearance=not no_appearance,
                                   out=dest, overwrite=overwrite)
    except ValueError as e:
        raise InputError(f"{e}; see rigsfm associate --help") from None
    with progress_bars() as progress:
        task = progress.add_task("associate", total=None)
        dest = associate(out, detections, options,
                         progress=lambda done, total: progress.update(task, completed=done, total=total))
    for line in frame_lines(dest):
        console.print(line)
    console.print(f"persons: {dest} (persons.csv / persons.json, floor.png, density per frame)")
    if Path(dest).resolve() == Workspace(out).associate.resolve():
        console.print(f"`rigsfm report {out}` adds them to its report.html")


def frame_lines(dest: Path, shown: int = 3) -> list[str]:
    """The first ``shown`` frames written into ``dest``, each its persons and the detections they hold; the rest
    in one line."""
    from rigsfm.associate.report import frame_counts

    counts = []
    for path in sorted(Path(dest).glob("*/persons.json")):
        data, assigned, total = frame_counts(path)
        counts.append((data["frame"], len(data["persons"]), assigned, total))
    shown = len(counts) if len(counts) <= shown + 1 else shown  # a line of its own, not a summary of one frame
    lines = [f"{frame}: {persons} persons from {assigned} of {total} detections"
             for frame, persons, assigned, total in counts[:shown]]
    if len(counts) > shown:
        rest = sorted(c[1] for c in counts[shown:])
        lines.append(f"... {len(rest)} more frames: {rest[len(rest) // 2]} persons (median), {rest[0]}-{rest[-1]}")
    return lines
