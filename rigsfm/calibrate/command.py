"""The ``rigsfm calibrate`` command; register with ``app.command("calibrate")(calibrate_command)``."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import typer

from rigsfm.calibrate import calibrate_rigs, write_calibration
from rigsfm.calibrate.board import load_board_spec
from rigsfm.calibrate.dataset import discover_rigs
from rigsfm.calibrate.intrinsics import DISTORTIONS
from rigsfm.calibrate.output import check_output
from rigsfm.core.errors import InputError

logger = logging.getLogger(__name__)


def calibrate_command(
    board_images: Annotated[Path, typer.Argument(help="Board images: BOARD/<rig>/wide/* and BOARD/<rig>/narrow/* "
                                                      "(same file name = same instant).")],
    board: Annotated[Path, typer.Option("--board", help="board.yaml: {type: chessboard, inner_corners: [9, 6], "
                                                        "square: 0.025} or {type: charuco, squares, square, marker, "
                                                        "dictionary} (metres).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="rigs.yaml to write.")],
    from_scene: Annotated[Path | None, typer.Option("--from-scene", help="SCENE/<rig>/{wide,narrow}: take the "
                                                       "E^sl rotation and translation direction from a textured scene.")] = None,
    baseline: Annotated[float | None, typer.Option("--baseline", help="Measured baseline length in metres "
                                                      "(replaces the board's).")] = None,
    merge: Annotated[bool, typer.Option("--merge", help="Add/replace these rigs in an existing rigs.yaml.")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing rigs.yaml (or, with --merge, "
                                                                "same-named rigs in it).")] = False,
    report_dir: Annotated[Path | None, typer.Option("--report-dir", help="Report folder (default: "
                                                       "<out stem>.calibration/ beside OUT).")] = None,
    distortion: Annotated[str, typer.Option("--distortion", help="auto (k3 only if it helps), opencv (k1 k2 p1 p2) "
                                                                 "or full_opencv (+k3).")] = "auto",
) -> None:
    """Calibrate each rig's wide and narrow intrinsics and E^sl (narrow_from_wide) from board images."""
    if distortion not in DISTORTIONS:
        raise InputError(f"--distortion must be one of {', '.join(DISTORTIONS)}, got {distortion!r}")
    spec = load_board_spec(board)
    names = [r.name for r in discover_rigs(board_images, "board images")]
    check_output(out, names, merge=merge, overwrite=overwrite)  # fail before the slow part
    result = calibrate_rigs(board_images, spec, distortion=distortion, scene_dir=from_scene, baseline=baseline)
    rigs_path, report = write_calibration(result, out, merge=merge, overwrite=overwrite, report_dir=report_dir)
    for rig in result.rigs:
        f = rig.stereo.final
        typer.echo(f"{rig.name}: wide f={f.K_wide[0, 0]:.1f}px RMS {rig.wide.rms:.3f}px, narrow f={f.K_narrow[0, 0]:.1f}px "
                   f"RMS {rig.narrow.rms:.3f}px, baseline {1000 * float((rig.T ** 2).sum() ** 0.5):.1f} mm, "
                   f"E^sl RMS {f.rms:.3f}px ({'joint' if rig.stereo.use_joint else 'fixed intrinsics'})")
    for warning in result.warnings:
        typer.echo(f"warning: {warning}", err=True)
    typer.echo(f"wrote {rigs_path} and {report}/")
