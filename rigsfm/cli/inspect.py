"""``rigsfm report``, ``rigsfm view`` and ``rigsfm export``."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Annotated

import typer

from rigsfm.cli.common import configure_logging, console, fail_cleanly, flag
from rigsfm.inspect.options import ExportFormat, ExportOptions

WORKSPACE = typer.Argument(metavar="OUT", help="workspace folder of a finished `rigsfm run`", show_default=False)


@fail_cleanly
def report_command(out: Annotated[Path, WORKSPACE]) -> None:
    """Write OUT/report.html: summary, reprojection errors, network plot, narrow pairs, epipolar check."""
    from rigsfm.core.workspace import Workspace
    from rigsfm.inspect.report.write import write_report

    configure_logging(False)  # a run that did not finish, said as a warning
    workspace = Workspace(out)
    workspace.require_result()  # before the lock, which makes the folder
    # not among the files of a run (or track) writing OUT now; a result copied without rigsfm's marks has no lock
    with workspace.lock() if workspace.is_ours() else contextlib.nullcontext():
        console.print(f"report: {write_report(out)}")


@fail_cleanly
def view_command(
    out: Annotated[Path, WORKSPACE],
    screenshot_path: Annotated[Path | None, typer.Option(
        "--screenshot", help="render the view headless into this PNG instead of opening a window (no display "
                             "needed)  [default: open a window; needs a display]", show_default=False)] = None,
    overwrite: Annotated[bool, flag("--overwrite", help="replace an existing --screenshot file")] = False,
) -> None:
    """Show the network in an Open3D window: points, wide (blue) and narrow (orange) frustums, each rig's
    wide-narrow link (green; a point when the baseline is centimetres) and the world axes (red x, green y, blue z).
    The window needs a display; --screenshot renders a PNG without one."""
    from rigsfm.inspect.viewer import screenshot, show

    if screenshot_path is not None:
        console.print(f"screenshot: {screenshot(out, screenshot_path, overwrite=overwrite)}")
    else:
        show(out)


@fail_cleanly
def export_command(
    out: Annotated[Path, WORKSPACE],
    fmt: Annotated[ExportFormat, typer.Option("--format", help="what to write", show_default=False)],
    dest: Annotated[Path | None, typer.Option(
        "--dest", help="folder to write: a new or empty one, or an earlier export  [default: OUT/export/FORMAT]",
        show_default=False)] = None,
    overwrite: Annotated[bool, flag("--overwrite", help="replace an earlier export in DEST (only the files rigsfm "
                                                        "wrote there are removed)")] = False,
    images: Annotated[bool, flag("--images", help="wildtrack: also write the narrow images, undistorted "
                                                  "(Image_subsets/<rig>/<frame>.png)")] = False,
    poses_from: Annotated[str | None, typer.Option(
        "--poses-from", metavar="FRAME",
        help="with --images: also the narrow images of frames the run was not given (a recording beside its images, "
             "as `rigsfm associate --poses-from`), undistorted with the cameras of its frame FRAME (static rigs)  "
             "[default: the run's frames only]", show_default=False)] = None,
) -> None:
    """Export the calibrated network for COLMAP, Open3D, nerfstudio, EasyMocap (opencv), aniposelib (toml),
    WILDTRACK / MVDet (wildtrack) or as plain JSON poses."""
    from rigsfm.inspect.export import export

    configure_logging(False)  # the files an --overwrite keeps, named as warnings
    options = ExportOptions(format=fmt, dest=dest, overwrite=overwrite, images=images, poses_from=poses_from)
    console.print(f"exported {fmt}: {export(out, options)}")
