"""Writing the calibration: rigs.yaml (optionally merged into an existing one) and the report folder.

Each rig is written as ``rigs.rigs_to_yaml`` writes it plus the uncertainty keys of ``uncertainty.py``
(``sigmas`` per sensor, ``sigma_rotation_deg``, ``sigma_translation_m``, ``covariance`` for E^sl). Rigs
that a merge keeps are copied from the existing file entry by entry, so their own uncertainties survive.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import yaml

from rigsfm.calibrate.report import write_report
from rigsfm.calibrate.uncertainty import add_sigmas, rig_sigmas
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import load_yaml_or_json, parse_yaml, write_text_atomic
from rigsfm.core.rig import RigCalibration, load_rigs, rigs_to_yaml

if TYPE_CHECKING:
    from rigsfm.calibrate.results import CalibrationResult

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
    new = result.rig_calibrations()
    existing = check_output(out, [r.name for r in new], merge=merge, overwrite=overwrite)
    report_dir = Path(report_dir) if report_dir is not None else default_report_dir(Path(out))
    write_report(result, report_dir, merge=merge, rigs_file=Path(out), overwrite=overwrite)
    write_text_atomic(Path(out), rigs_yaml_text(result, existing, Path(out)), overwrite=True)
    logger.info("wrote %s (%d rigs) and the report in %s", out, len(new), report_dir)
    return Path(out), report_dir


def rigs_yaml_text(result: CalibrationResult, existing: list[RigCalibration], out: Path) -> str:
    """rigs.yaml with ``result``'s rigs and their uncertainties, after the ``existing`` rigs a merge keeps."""
    new = result.rig_calibrations()
    entries = parse_yaml(rigs_to_yaml(new))["rigs"] if new else []
    by_name = {e["name"]: add_sigmas(e, rig_sigmas(rig)) for e, rig in zip(entries, result.rigs)}
    kept = {}
    if existing:  # the entries as they are in the file (validated by load_rigs in check_output)
        kept = {e["name"]: e for e in load_yaml_or_json(out, "rig calibration")["rigs"]}
    rigs = [r.name for r in merged(existing, new)]
    data = {"units": "meters", "rigs": [by_name[n] if n in by_name else kept[n] for n in rigs]}
    if out.suffix.lower() == ".json":  # rigs.yaml may be JSON: a file named so must read with any JSON reader
        return json.dumps(data, indent=2) + "\n"
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)
