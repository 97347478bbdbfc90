"""``rigsfm report OUT``: OUT/report.html, one self-contained page to inspect and trust a calibration.

Summary (rigs, registration, scale residuals, timings), reprojection error per camera with histograms, a
top view of the network, the narrow pairs in the paper's format with F_ji and the 95 % epipolar band, and
an epipolar check figure per narrow pair (points in narrow image i, their lines and bands in image j).
"""

from __future__ import annotations

import logging
from pathlib import Path

import pycolmap

from rigsfm.core.io import write_text_atomic
from rigsfm.core.summary import Summary
from rigsfm.core.workspace import Workspace
from rigsfm.inspect.report.html import render_page

logger = logging.getLogger(__name__)


def load_result(out: Path) -> tuple[pycolmap.Reconstruction, dict, Summary | None]:
    """The final model, narrow_poses.json and (if present) summary.json of a workspace."""
    workspace = Workspace(Path(out))
    workspace.require_result()
    narrow = workspace.read_narrow_poses()
    return workspace.read_sparse(), narrow, Summary.read(workspace.summary)


def write_report(out: Path) -> Path:
    """Write ``out/report.html`` from the workspace's results (replacing an older report) and return it."""
    workspace = Workspace(Path(out))
    reconstruction, narrow, summary = load_result(workspace.root)
    workspace.warn_unfinished()
    page = render_page(workspace.root, summary, reconstruction, narrow)
    path = write_text_atomic(workspace.report, page)
    logger.info("Wrote %s (%.1f kB)", path, path.stat().st_size / 1e3)
    return path
