"""``rigsfm report OUT``: OUT/report.html, one self-contained page to inspect and trust a calibration.

Summary (rigs, registration, scale residuals, timings), reprojection error per camera with histograms, a
top view of the network, the narrow pairs in the paper's format with F_ji and the 95 % epipolar band, and
an epipolar check figure per narrow pair (points in narrow image i, their lines and bands in image j).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated

import pycolmap
import typer

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import write_text_atomic
from rigsfm.inspect.report.html import load_json, render_page
from rigsfm.core.workspace import Workspace

logger = logging.getLogger(__name__)

REPORT_NAME = "report.html"


def load_result(out: Path) -> tuple[pycolmap.Reconstruction, dict, dict | None]:
    """The final model, narrow_poses.json and (if present) summary.json of a workspace."""
    workspace = Workspace(Path(out))
    if not (workspace.sparse / "images.bin").is_file() and not (workspace.sparse / "images.txt").is_file():
        raise WorkspaceError(f"{workspace.root} holds no result ({workspace.sparse} is missing): run `rigsfm run` first")
    if not workspace.narrow_poses.is_file():
        raise WorkspaceError(f"{workspace.narrow_poses} is missing: re-run `rigsfm run --overwrite`")
    return (pycolmap.Reconstruction(str(workspace.sparse)), load_json(workspace.narrow_poses),
            load_json(workspace.summary))


def write_report(out: Path) -> Path:
    """Write ``out/report.html`` from the workspace's results (replacing an older report) and return it."""
    out = Path(out)
    reconstruction, narrow, summary = load_result(out)
    page = render_page(out, summary, reconstruction, narrow)
    path = write_text_atomic(out / REPORT_NAME, page)
    logger.info("Wrote %s (%.1f kB)", path, path.stat().st_size / 1e3)
    return path


def report_command(
    out: Annotated[Path, typer.Argument(help="workspace folder of a finished `rigsfm run`")],
) -> None:
    """Write OUT/report.html: summary, reprojection errors, network plot, narrow pairs, epipolar check."""
    path = write_report(out)
    typer.echo(f"report: {path}")
