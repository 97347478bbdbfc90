"""Calibration report: a text summary per rig plus PNG plots drawn with OpenCV (no matplotlib).

``report_dir/<rig>/report.txt``, ``{wide,narrow}_view_errors.png`` (per-view RMS bars, rejected views in
red, median and outlier threshold lines), ``{wide,narrow}_coverage.png`` (every used corner, per-view
convex hulls, covered grid cells shaded) and ``stereo_view_errors.png``; ``report_dir/summary.txt``.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from rigsfm.calibrate.intrinsics import COVERAGE_GRID, OUTLIER_FACTOR, CameraCalibration
from rigsfm.calibrate.stereo import StereoFit
from rigsfm.core import charts
from rigsfm.core.conventions import euler_zyx_degrees
from rigsfm.core.errors import WorkspaceError
from rigsfm.core.io import atomic_directory, sha256_file, write_json_atomic, write_text_atomic

if TYPE_CHECKING:
    from rigsfm.calibrate.results import CalibrationResult, RigResult

logger = logging.getLogger(__name__)


def view_error_chart(cam: CameraCalibration, where: str) -> np.ndarray:
    views = [v for v in cam.views if v.rms is not None]
    used: list = [v.rms for v in cam.views if v.used]
    median = float(np.median(used)) if used else 0.0
    return charts.bar_chart(f"{where}: per-view RMS reprojection error (red = rejected)", [v.name for v in views],
                            [[v.rms for v in views]], [["good" if v.used else "bad" for v in views]],
                            [(median, "muted", "median"), (OUTLIER_FACTOR * median, "warn",
                                                           f"{OUTLIER_FACTOR:g} x median")])


def coverage_image(cam: CameraCalibration, where: str, max_side: int = 800) -> np.ndarray:
    w, h = cam.image_size
    s = max_side / max(w, h)
    image = charts.canvas(round(w * s), round(h * s))
    cols, rows = COVERAGE_GRID
    points = [pairs[1].reshape(-1, 2) for pairs in cam.pairs.values()]
    allp = np.vstack(points) if points else np.zeros((0, 2))
    for r in range(rows):
        for c in range(cols):
            x0, x1, y0, y1 = c * w / cols, (c + 1) * w / cols, r * h / rows, (r + 1) * h / rows
            hit = np.any((allp[:, 0] >= x0) & (allp[:, 0] < x1) & (allp[:, 1] >= y0) & (allp[:, 1] < y1))
            p0, p1 = (int(x0 * s), int(y0 * s)), (int(x1 * s) - 1, int(y1 * s) - 1)
            if hit:
                cv2.rectangle(image, p0, p1, charts.bgr((225, 245, 225)), -1)
            cv2.rectangle(image, p0, p1, charts.bgr("grid"), 1)
    for k, pts in enumerate(points):
        colour = charts.bgr(charts.SERIES[k % len(charts.SERIES)])
        hull = cv2.convexHull((pts * s).astype(np.int32))
        cv2.polylines(image, [hull], True, colour, 1, cv2.LINE_AA)
        for x, y in pts * s:
            cv2.circle(image, (int(x), int(y)), 2, colour, -1, cv2.LINE_AA)
    charts.text(image, f"{where}: corner coverage {100 * cam.coverage:.0f} % of {cols}x{rows} cells, "
                f"{len(points)} views", (10, 22), size=0.55)
    return image


def stereo_chart(rig: RigResult) -> np.ndarray:
    fit = rig.stereo.final
    names = sorted(fit.per_view)
    return charts.bar_chart(f"rig {rig.name}: stereo per-view RMS (blue = wide, orange = narrow)", names,
                            [[fit.per_view[n][0] for n in names], [fit.per_view[n][1] for n in names]],
                            [["wide"] * len(names), ["narrow"] * len(names)], [(fit.rms, "muted", "overall RMS")])


def _camera_text(cam: CameraCalibration, K: np.ndarray, dist: np.ndarray, label: str) -> list[str]:
    std = cam.std_intrinsics
    lines = [f"{label} camera: {cam.image_size[0]}x{cam.image_size[1]}, COLMAP model {cam.model}",
             f"  fx, fy = {K[0, 0]:.3f}, {K[1, 1]:.3f} px (mono std {std[0]:.3f}, {std[1]:.3f})",
             (f"  cx, cy = {K[0, 2]:.3f}, {K[1, 2]:.3f} px OpenCV convention "
             f"(= {K[0, 2] + 0.5:.3f}, {K[1, 2] + 0.5:.3f} in COLMAP's, as written to rigs.yaml)"),
             "  distortion k1 k2 p1 p2 k3 = " + " ".join(f"{v:.6g}" for v in np.ravel(dist)[:5]),
             f"  mono RMS {cam.rms:.4f} px over {len(cam.used_views)} views; corner coverage {100 * cam.coverage:.0f} %"]
    lines += [f"  note: {n}" for n in cam.notes] + [f"  WARNING: {w}" for w in cam.warnings]
    lines.append("  views (name, corners, RMS px, status):")
    for v in cam.views:
        rms = "-" if v.rms is None else f"{v.rms:.3f}"
        lines.append(f"    {v.name:<16} {v.corners:>4} {rms:>8}  {'used' if v.used else 'rejected: ' + v.reason}")
    return lines


def _pose_text(fit: StereoFit, label: str) -> list[str]:
    angle = float(np.degrees(np.linalg.norm(cv2.Rodrigues(fit.R)[0])))
    yaw, pitch, roll = euler_zyx_degrees(fit.R)
    t = fit.T * 1000
    return [(f"  {label}: RMS {fit.rms:.4f} px, rotation {angle:.4f} deg (yaw/pitch/roll {yaw:.4f}/{pitch:.4f}/"
            f"{roll:.4f} deg), t = [{t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}] mm, baseline {fit.baseline * 1000:.2f} mm")]


def rig_text(rig: RigResult, board_description: str) -> str:
    st = rig.stereo
    final = st.final
    lines = [f"Rig {rig.name}", f"Board: {board_description}", ""]
    lines += _camera_text(rig.wide, final.K_wide, final.dist_wide, "wide") + [""]
    lines += _camera_text(rig.narrow, final.K_narrow, final.dist_narrow, "narrow") + [""]
    lines.append(f"E^sl narrow_from_wide (x_narrow = R x_wide + t) from {len(st.views)} common views:")
    lines += _pose_text(st.fixed, "intrinsics fixed")
    if st.joint is not None:
        lines += _pose_text(st.joint, "joint refinement")
        d = st.joint_detail
        if d is not None:
            lines.append(f"    joint std fx fy cx cy (independent corner errors): wide "
                         f"{' '.join(f'{v:.3f}' for v in d.std[:4])}, narrow "
                         f"{' '.join(f'{v:.3f}' for v in d.std[4:])} px; per-camera RMS {d.rms_wide:.3f} / "
                         f"{d.rms_narrow:.3f} px; condition {d.condition:.2g}")
            lines.append("    (a narrow principal-point error dp shifts the E^sl rotation by about dp / f_narrow rad)")
    lines += [f"  note: {n}" for n in st.notes]
    lines += [f"  view {n} not used for E^sl: {r}" for n, r in sorted(st.dropped.items())]
    if rig.scene is not None:
        sc = rig.scene
        lines.append(f"  scene: {sc.matches} SIFT matches (narrow downscaled x{sc.scale:.3f}), {sc.inliers} inliers, "
                     f"Sampson RMS {sc.rms_px:.3f} wide px")
    lines += [f"  note: {n}" for n in rig.notes]
    R, t = rig.R, rig.T
    lines += ["", "Written to rigs.yaml (narrow_from_wide):",
              "  rotation: " + "; ".join(" ".join(f"{v:.8f}" for v in row) for row in R),
              "  translation (m): " + " ".join(f"{v:.6f}" for v in t) + f"   baseline {np.linalg.norm(t):.6f} m"]
    lines += [""] + _sigma_text(rig)
    return "\n".join(lines) + "\n"


PARAM_NAMES = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"]


def _sigma_text(rig: RigResult) -> list[str]:
    sigmas = rig.sigmas()
    lines = ["Uncertainties written to rigs.yaml (1 sigma, from the joint refinement's covariance):"]
    for sensor in ("wide", "narrow"):
        values = sigmas.sensor(sensor)
        if values is not None:
            lines.append(f"  {sensor} sigmas: " + ", ".join(f"{n} {v:.3g}" for n, v in zip(PARAM_NAMES, values)))
    if sigmas.rotation_deg is not None:
        lines.append("  E^sl rotation sigma (deg, R_true = Exp(w) R, w in narrow axes): "
                     + " ".join(f"{v:.4f}" for v in sigmas.rotation_deg))
    if sigmas.translation_m is not None:
        lines.append("  E^sl translation sigma (mm): " + " ".join(f"{1000 * v:.3f}" for v in sigmas.translation_m))
    lines += [f"  note: {n}" for n in sigmas.notes]
    detail = rig.stereo.joint_detail
    if rig.stereo.use_joint and detail is not None and detail.covariance is not None:
        lines.append(f"  corner noise estimated from the fit: wide {detail.noise[0]:.3f}, narrow {detail.noise[1]:.3f} px; "
                     "sigmas for independent corner errors x " + " / ".join(f"{v:.2f}" for v in detail.inflation)
                     + " (wide / narrow / E^sl: the leave-one-frame-out jackknife's excess, >= 1)")
        names = ([f"wide {n}" for n in PARAM_NAMES[:detail.n_wide]] + [f"narrow {n}" for n in PARAM_NAMES[:detail.n_narrow]]
                 + ["E^sl w_x", "E^sl w_y", "E^sl w_z", "E^sl t_x", "E^sl t_y", "E^sl t_z"])
        part = np.repeat([0, 1, 2], [detail.n_wide, detail.n_narrow, 6])
        std = np.sqrt(np.clip(np.diag(detail.covariance), 1e-300, None))
        corr = detail.covariance / np.outer(std, std)
        pairs = sorted(((abs(corr[i, j]), i, j) for i in range(len(std)) for j in range(i) if part[i] != part[j]),
                       reverse=True)
        strong = [f"{names[j]} / {names[i]} {corr[i, j]:+.3f}" for c, i, j in pairs[:4] if c > 0.5]
        if strong:
            lines.append("  strongest correlations across wide / narrow / E^sl (not in rigs.yaml): " + "; ".join(strong))
    return lines


REPORT_FILES = frozenset({"report.txt", "stereo_view_errors.png", "wide_view_errors.png", "narrow_view_errors.png",
                          "wide_coverage.png", "narrow_coverage.png"})  # a rig's folder: all a new report replaces
SUMMARY_START = b"Board: "  # summary.txt's first words: a summary.txt that lacks them is not rigsfm's
RIG_LINE = ": wide RMS "  # after a rig's name, its line of summary.txt: the rigs whose folders it wrote
MANIFEST = ".rigsfm-calibration.json"  # the rigs file a report is of, and the files written with their SHA-256


def _is_our_summary(path: Path) -> bool:
    """Whether summary.txt begins as :func:`write_report` writes it."""
    with open(path, "rb") as handle:
        return handle.read(len(SUMMARY_START)) == SUMMARY_START


def read_manifest(report_dir: Path) -> tuple[str | None, dict[str, str]] | None:
    """(the rigs file, the SHA-256 of each file written) a report in ``report_dir`` recorded; None for none."""
    path = Path(report_dir) / MANIFEST
    try:
        data = json.loads(path.read_text(encoding="utf-8")) if path.is_file() and not path.is_symlink() else None
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("sha256"), dict):
        return None
    return data.get("rigs_file"), {k: v for k, v in data["sha256"].items() if isinstance(v, str)}


def _still_written(report_dir: Path, name: str, sums: dict[str, str]) -> bool:
    """Whether ``report_dir/name`` is a plain file as a report wrote it (its recorded SHA-256)."""
    path = Path(report_dir) / name
    return not path.is_symlink() and path.is_file() and sums.get(name) == sha256_file(path)


def _rigs_file_key(rigs_file: Path | None) -> str | None:
    return None if rigs_file is None else str(Path(rigs_file).resolve())


def check_report_dir(report_dir: Path, rig_names: list[str], *, rigs_file: Path | None = None,
                     overwrite: bool = False) -> None:
    """Refuse a report folder holding the report of another rigs file than ``rigs_file`` (without ``overwrite``),
    a rig's report folder that holds anything a new report would not write again (it replaces the folder whole),
    and a file of the report's names that a report did not write (or changed since): the user's files are never
    removed or replaced."""
    recorded = read_manifest(report_dir)
    sums = recorded[1] if recorded is not None else {}
    if recorded is not None and recorded[0] != _rigs_file_key(rigs_file) and not overwrite:
        raise WorkspaceError(f"'{report_dir}' holds the report of another calibration ({recorded[0]}): pass "
                             "--overwrite to replace it or choose another --report-dir (nothing was written)")
    summary = Path(report_dir) / "summary.txt"
    if os.path.lexists(summary) and not _still_written(report_dir, "summary.txt", sums):
        raise WorkspaceError(f"'{summary}' is not a summary rigsfm calibrate wrote; move it away or choose another "
                             "--report-dir (nothing was written)")
    for name in rig_names:
        folder = Path(report_dir) / name
        if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
            raise WorkspaceError(f"{folder} exists and is not a report folder; move it away or choose another "
                                 "--report-dir (nothing was written)")
        foreign = sorted(p.name for p in folder.iterdir() if p.name not in REPORT_FILES or not p.is_file()
                         or p.is_symlink()) if folder.is_dir() else []
        if foreign:
            raise WorkspaceError(f"'{folder}' holds files rigsfm did not write ({', '.join(foreign[:3])}"
                                 f"{', ...' if len(foreign) > 3 else ''}); move them away or choose another "
                                 "--report-dir (nothing was written)")
        changed = sorted(p for p in folder.iterdir() if not _still_written(report_dir, f"{name}/{p.name}", sums)) \
            if folder.is_dir() else []
        if changed:
            raise WorkspaceError(f"'{changed[0]}' is not a file rigsfm calibrate wrote (or it changed since); move "
                                 "it away or choose another --report-dir (nothing was written)")


def _summary_lines(path: Path) -> dict[str, list[str]]:
    """Per rig a summary.txt :func:`write_report` wrote names, its lines (``NAME: wide RMS ...`` and its warnings
    below it); none where it did not write one."""
    if path.is_symlink() or not path.is_file() or not _is_our_summary(path):
        return {}
    lines: dict[str, list[str]] = {}
    rig = None
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line[:1].isspace():
            rig = line.split(RIG_LINE, 1)[0] if RIG_LINE in line else None
        if rig is not None:
            lines.setdefault(rig, []).append(line)
    return lines


def _report_files(folder: Path) -> list[Path] | None:
    """The files of a rig's report folder, None where it holds anything a report does not (or is no folder)."""
    if folder.is_symlink() or not folder.is_dir():
        return None
    files = list(folder.iterdir())
    if not files or any(p.name not in REPORT_FILES or p.is_symlink() or not p.is_file() for p in files):
        return None
    return files


def remove_rigs_no_longer_calibrated(report_dir: Path, written: set[str], calibrated: set[str],
                                     sums: dict[str, str]) -> list[Path]:
    """Remove the report folders of the rigs an earlier report in ``report_dir`` wrote (``written``: its
    summary.txt names them) that this calibration (``calibrated``) no longer has, where they hold only a report's
    files as written (``sums``: their recorded SHA-256, whose entries go with them); a folder that holds other
    files, or looks like a rig's report but no summary of rigsfm's names it, is left, named in one warning line.
    Returns the folders removed."""
    removed, left = [], []
    for folder in sorted(p for p in report_dir.iterdir() if p.name not in calibrated and not p.name.startswith(".")):
        files = _report_files(folder)
        ours = files is not None and all(_still_written(report_dir, f"{folder.name}/{p.name}", sums) for p in files)
        if folder.name in written and files is not None and ours:
            for file in files:  # each a report's file: never the folder whole
                file.unlink()
                sums.pop(f"{folder.name}/{file.name}", None)
            folder.rmdir()
            removed.append(folder)
        elif folder.name in written or files is not None:
            left.append(folder)
    if removed:
        logger.info("Removed the reports of rig(s) this calibration no longer has: %s",
                    ", ".join(str(p) for p in removed))
    if left:
        logger.warning("%s: report folder(s) of rig(s) this calibration does not have, left as they are (rigsfm "
                       "removes only those its summary.txt names that hold only a report's files); remove them if "
                       "they are stale", ", ".join(f"'{p}'" for p in left))
    return removed


def write_report(result: CalibrationResult, report_dir: Path, *, merge: bool = False, rigs_file: Path | None = None,
                 overwrite: bool = False) -> Path:
    """The calibration's report in ``report_dir``: a folder per rig and summary.txt, and the manifest naming
    ``rigs_file`` (a report of another is replaced only with ``overwrite``) and the files written. Without ``merge``
    (the rigs replace rigs.yaml's), the folders an earlier report wrote of rigs this one lacks are removed; with it,
    their lines of the earlier summary.txt are kept (rigs.yaml keeps them)."""
    report_dir = Path(report_dir)
    # every rig first: a refusal changes nothing
    check_report_dir(report_dir, [rig.name for rig in result.rigs], rigs_file=rigs_file, overwrite=overwrite)
    earlier = _summary_lines(report_dir / "summary.txt")  # before this report replaces it
    written = set(earlier)
    report_dir.mkdir(parents=True, exist_ok=True)
    sums = dict((read_manifest(report_dir) or (None, {}))[1])

    def record() -> None:  # after each file or folder: a stopped report's re-run knows what it wrote
        write_json_atomic(report_dir / MANIFEST, {"written_by": "rigsfm calibrate",
                                                  "rigs_file": _rigs_file_key(rigs_file), "sha256": sums})

    record()
    summary = [f"{SUMMARY_START.decode()}{result.board.describe()}", ""]
    for rig in result.rigs:
        with atomic_directory(report_dir / rig.name, overwrite=True) as tmp:
            (tmp / "report.txt").write_text(rig_text(rig, result.board.describe()), encoding="utf-8")
            for cam in (rig.wide, rig.narrow):
                cv2.imwrite(str(tmp / f"{cam.sensor}_view_errors.png"), view_error_chart(cam, f"{rig.name} {cam.sensor}"))
                cv2.imwrite(str(tmp / f"{cam.sensor}_coverage.png"), coverage_image(cam, f"{rig.name} {cam.sensor}"))
            cv2.imwrite(str(tmp / "stereo_view_errors.png"), stereo_chart(rig))
        sums.update({f"{rig.name}/{p.name}": sha256_file(p) for p in (report_dir / rig.name).iterdir()})
        record()
        f = rig.stereo.final
        summary.append(f"{rig.name}{RIG_LINE}{rig.wide.rms:.3f} px, narrow RMS {rig.narrow.rms:.3f} px, E^sl RMS "
                       f"{f.rms:.3f} px, baseline {np.linalg.norm(rig.T) * 1000:.2f} mm"
                       f"{' (scene rotation)' if rig.scene else ''}; {len(rig.warnings)} warnings")
        summary += [f"  WARNING: {w}" for w in rig.warnings]
    if merge:  # the rigs a merge keeps keep their lines: a later --overwrite knows it wrote their folders
        calibrated = {rig.name for rig in result.rigs}
        summary += [line for rig, lines in earlier.items() if rig not in calibrated for line in lines]
    else:  # before the summary that names them goes: a stop between the two leaves them named
        remove_rigs_no_longer_calibrated(report_dir, written, {rig.name for rig in result.rigs}, sums)
    write_text_atomic(report_dir / "summary.txt", "\n".join(summary) + "\n")
    sums["summary.txt"] = sha256_file(report_dir / "summary.txt")
    record()
    return report_dir
