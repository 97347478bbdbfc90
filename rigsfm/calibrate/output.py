"""Writing the calibration: rigs.yaml (optionally merged into an existing one) and the report folder."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

from rigsfm.core.errors import WorkspaceError
from rigsfm.core.rig import RigCalibration, load_rigs, write_rigs

if TYPE_CHECKING:
    from rigsfm.calibrate import CalibrationResult

logger = logging.getLogger(__name__)


def default_report_dir(out: Path) -> Path:
    """``rigs.yaml`` -> ``rigs.calibration/`` beside it."""
    return out.with_name(f"{out.stem}.calibration")


def check_output(out: Path, rig_names: list[str], *, merge: bool, overwrite: bool) -> list[RigCalibration]:
    """Refuse early what the write would refuse later; returns the existing rigs a merge keeps."""
    out = Path(out)
    if out.exists() and out.is_dir():
        raise WorkspaceError(f"{out} is a folder; give the path of the rigs.yaml file to write")
    if not out.exists():
        return []
    if not merge:
        if not overwrite:
            raise WorkspaceError(f"{out} already exists: pass --overwrite to replace it or --merge to add these rigs to it")
        return []
    existing = load_rigs(out)
    clashes = sorted({r.name for r in existing} & set(rig_names))
    if clashes and not overwrite:
        raise WorkspaceError(f"{out} already has rig(s) {', '.join(clashes)}: pass --overwrite (with --merge) to "
                             "replace them")
    return existing


def merged(existing: list[RigCalibration], new: list[RigCalibration]) -> list[RigCalibration]:
    """Existing rigs in their order with same-named ones replaced, then the new ones."""
    by_name = {r.name: r for r in new}
    out = [by_name.pop(r.name, r) for r in existing]
    return out + [r for r in new if r.name in by_name]


def write_outputs(result: CalibrationResult, out: Path, *, merge: bool = False, overwrite: bool = False,
                  report_dir: Path | None = None) -> tuple[Path, Path]:
    from rigsfm.calibrate.report import write_report

    new = result.rig_calibrations()
    existing = check_output(out, [r.name for r in new], merge=merge, overwrite=overwrite)
    report_dir = Path(report_dir) if report_dir is not None else default_report_dir(Path(out))
    write_report(result, report_dir)
    write_rigs(Path(out), merged(existing, new), overwrite=True)
    logger.info("wrote %s (%d rigs) and the report in %s", out, len(new), report_dir)
    return Path(out), report_dir
