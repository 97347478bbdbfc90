"""``rigsfm associate``."""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Annotated

import typer

from rigsfm.cli.common import configure_logging, console, fail_cleanly, flag, progress_bars
from rigsfm.core.errors import InputError
from rigsfm.core.names import quoted
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
    pixel_sigma: Annotated[float | None, typer.Option(
        "--pixel-sigma", min=0.01, metavar="PX",
        help="the detector's noise per coordinate (px) [default: estimated from the persons of the first frame]",
        show_default=False)] = None,
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
    poses_from: Annotated[str | None, typer.Option(
        "--poses-from", metavar="FRAME",
        help="associate frames the run was not given with the narrow poses of its frame FRAME (e.g. frame0000.png): "
             "static rigs calibrated once; `rigsfm track` checks they have not moved  [default: none: such frames "
             "are refused]", show_default=False)] = None,
    frame_offsets: Annotated[str | None, typer.Option(
        "--frame-offsets", metavar="auto|FILE|off",
        help="unsynchronised rigs: auto estimates each rig's frame offset from the persons and pairs the frames by "
             "time; FILE (yaml 'rig03: 1': rig03's frame k was taken at the others' frame k+1) applies given ones; "
             "off skips the check [default: a recording of three frames or more is checked and a rig off in time "
             "named]", show_default=False)] = None,
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
        options = AssociateOptions(heights=parse_heights(heights, example="1.0-2.1"), pixel_sigma=pixel_sigma,
                                   detection_probability=detection_probability, size_noise=size_noise,
                                   self_calibration_rounds=self_calibration_rounds, walk_m=walk or None,
                                   appearance=not no_appearance, poses_from=poses_from,
                                   frame_offsets=frame_offsets,
                                   out=dest, overwrite=overwrite)
    except ValueError as e:
        raise InputError(f"{e}; see rigsfm associate --help") from None
    with progress_bars() as progress:
        task = progress.add_task("associate", total=None)
        dest = associate(out, detections, options,
                         progress=lambda done, total: progress.update(task, completed=done, total=total))
    frames = written_frames(dest)
    for line in frame_lines(frames):
        console.print(line)
    for line in lent_lines(frames, poses_from, out):
        console.print(line)
    offsets = offsets_line(dest)
    if offsets:
        console.print(offsets)
    tracked = tracks_line(dest)
    if tracked:
        console.print(tracked)
    console.print(f"persons: {dest} (persons.csv / persons.json, floor.png, density per frame)")
    if Path(dest).resolve() == Workspace(out).associate.resolve():
        console.print(f"`rigsfm report {out}` adds them to its report.html")


def written_frames(dest: Path) -> list[tuple[str, int, int, int, str | None, list[str]]]:
    """Per frame written into ``dest``: its name, persons, the detections they hold, all its detections, the run's
    frame whose poses it took (None: its own), and where only some of its views took them (a frame of the run that
    lacked their narrow images), those views (else empty)."""
    from rigsfm.associate.report import frame_counts, lent_views

    frames = []
    for path in sorted(Path(dest).glob("*/persons.json")):
        data, assigned, total = frame_counts(path)
        lent = lent_views(data)
        # a frame of the run: a view of its own file name kept its pose (frames paired by time hold other frames')
        own = [v for v in data.get("views") or [] if v not in lent and v.endswith("/" + str(data["frame"]))]
        partly = lent if own else []
        frames.append((data["frame"], len(data["persons"]), assigned, total, data.get("poses_from"), partly))
    return frames


def lent_lines(frames: list[tuple[str, int, int, int, str | None, list[str]]], poses_from: str | None,
               out: Path) -> list[str]:
    """Which frames of :func:`written_frames` took the narrow poses of ``poses_from``: the frames the run was not
    given, and apart from them the run's own frames some of whose narrow images it was not given."""
    whole = sum(poses is not None and not partly for *_, poses, partly in frames)
    partial = [(frame, partly) for frame, *_, partly in frames if partly]
    lines = []
    if whole:
        lines.append(f"{whole} frame(s) the run was not given: associated with the narrow poses of its frame "
                     f"{poses_from} (static rigs; `rigsfm track {out} IMAGES` tells whether a rig moved)")
    if partial:
        first, views = partial[0]
        lines.append(f"{len(partial)} frame(s) of the run without some of their narrow images (e.g. {first}: "
                     f"{quoted(views[:3])}{' ...' if len(views) > 3 else ''}): those views took the narrow poses of "
                     f"its frame {poses_from}, the others their own")
    return lines


def frame_lines(frames: list[tuple[str, int, int, int, str | None, list[str]]], shown: int = 3) -> list[str]:
    """The first ``shown`` of :func:`written_frames`, each its persons and the detections they hold; the rest in one
    line."""
    shown = len(frames) if len(frames) <= shown + 1 else shown  # a line of its own, not a summary of one frame
    lines = [f"{frame}: {persons} persons from {assigned} of {total} detections"
             for frame, persons, assigned, total, *_ in frames[:shown]]
    if len(frames) > shown:
        rest = sorted(c[1] for c in frames[shown:])
        lines.append(f"... {len(rest)} more frames: {rest[len(rest) // 2]} persons (median), {rest[0]}-{rest[-1]}")
    return lines


def tracks_line(dest: Path) -> str | None:
    """How the persons of a recording's frames go on from the frame before's (persons.json's ``track`` and
    ``after``): their share and median step on the floor; None for one frame."""
    import json

    from rigsfm.associate.trajectories import TRACK_CONFIDENCE

    steps, persons, going_on = [], 0, 0
    before = None
    frames = [json.loads(path.read_text(encoding="utf-8")) for path in Path(dest).glob("*/persons.json")]
    for data in sorted(frames, key=lambda d: str(d.get("frame"))):  # the order they were linked in (by frame name)
        if before is not None:
            persons += len(data["persons"])
            for person in data["persons"]:
                if (person.get("after_confidence") or 0.0) > TRACK_CONFIDENCE:
                    going_on += 1
                    was = before[person["after"]]["position_m"]
                    steps.append(math.dist(person["position_m"][:2], was[:2]))
        before = data["persons"]
    if not persons:
        return None
    share = going_on / persons
    line = f"tracks: {share:.0%} of the later frames' persons go on from the frame before"
    if steps:
        line += f" (a median step of {statistics.median(steps):.2f} m a frame)"
    line += "; persons.json `track`, `after`"
    if share < 0.3:
        line += ("; the crowd walks too far between frames to tell who is who, so most tracks break: a higher "
                 "frame rate links them")
    return line


def offsets_line(dest: Path) -> str | None:
    """The frame-offsets check's line (rigsfm.associate.sync), from the manifest; None where it did not run."""
    import json

    from rigsfm.associate.output import MANIFEST
    from rigsfm.associate.sync import NOT_A_RECORDING, describe

    try:
        record = json.loads((Path(dest) / MANIFEST).read_text(encoding="utf-8")).get("frame_offsets")
    except (OSError, ValueError):
        return None
    if not record or record["asked"] == "check" and record["skipped"] == NOT_A_RECORDING:
        return None  # a frame or two, not asked about: nothing to say (a recording the check could not test is said)
    return describe(record)
