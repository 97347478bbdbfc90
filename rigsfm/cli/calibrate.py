"""``rigsfm calibrate``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from rigsfm.calibrate.options import CalibrateOptions, Distortion
from rigsfm.cli.common import configure_logging, console, err_console, fail_cleanly, flag, styled


@fail_cleanly
def calibrate_command(
    board_images: Annotated[Path, typer.Argument(metavar="BOARD_IMAGES", help="board images: BOARD/<rig>/wide/* and BOARD/<rig>/narrow/* "
                                                      "(same file name = same instant)", show_default=False)],
    board: Annotated[Path, typer.Option("--board", help="board.yaml: {type: chessboard, inner_corners: [9, 6], "
                                                        "square: 0.025} or {type: charuco, squares, square, marker, "
                                                        "dictionary} (metres)", show_default=False)],
    out: Annotated[Path, typer.Option("--out", "-o", help="rigs.yaml to write", show_default=False)],
    from_scene: Annotated[Path | None, typer.Option(
        "--from-scene", help="SCENE/<rig>/{wide,narrow}: take the E^sl rotation and translation direction from a "
                             "textured scene  [default: from the board]", show_default=False)] = None,
    baseline: Annotated[float | None, typer.Option(
        "--baseline", min=0.0, metavar="M", help="measured baseline length in metres  [default: the board's]",
        show_default=False)] = None,
    merge: Annotated[bool, flag("--merge", help="add/replace these rigs in an existing rigs.yaml")] = False,
    overwrite: Annotated[bool, flag("--overwrite", help="replace an existing rigs.yaml (or, with --merge, same-named "
                                                        "rigs in it)")] = False,
    report_dir: Annotated[Path | None, typer.Option(
        "--report-dir", help="report folder  [default: <out stem>.calibration/ beside OUT]", show_default=False)] = None,
    distortion: Annotated[Distortion, typer.Option(
        "--distortion", help="auto (k3 only if it helps), opencv (k1 k2 p1 p2) or full_opencv (+k3)")] = Distortion.AUTO,
) -> None:
    """Calibrate each rig's wide and narrow intrinsics and E^sl (narrow_from_wide) from board images."""
    from rigsfm.calibrate.pipeline import calibrate

    configure_logging(False)  # the report folders an --overwrite leaves, named as warnings
    options = CalibrateOptions(board=board, distortion=distortion, scene_dir=from_scene, baseline=baseline,
                               merge=merge, overwrite=overwrite, report_dir=report_dir)
    result, rigs_path, report = calibrate(board_images, out, options)
    for rig in result.rigs:
        f = rig.stereo.final
        console.print(f"{rig.name}: wide f={f.K_wide[0, 0]:.1f}px RMS {rig.wide.rms:.3f}px, narrow f={f.K_narrow[0, 0]:.1f}px "
                      f"RMS {rig.narrow.rms:.3f}px, baseline {1000 * float((rig.T ** 2).sum() ** 0.5):.1f} mm, "
                      f"E^sl RMS {f.rms:.3f}px ({'joint' if rig.stereo.use_joint else 'fixed intrinsics'})")
    for warning in result.warnings:
        err_console.print(styled("warning:", "bold yellow", warning), soft_wrap=True)
    console.print(f"wrote {rigs_path} and {report}/")
