"""``rigsfm calibrate``: intrinsics of both cameras of each rig and E^sl from calibration-board images.

Library use::

    from rigsfm.calibrate import calibrate_rigs, load_board_spec, write_calibration
    result = calibrate_rigs(Path("BOARD"), load_board_spec(Path("board.yaml")))
    write_calibration(result, Path("rigs.yaml"))           # + report in rigs.calibration/

Steps per rig: detect the board in every image (ChArUco: any part of it), calibrate each camera on all its
views (outlier views rejected with a reason), estimate E^sl with intrinsics fixed on the views both cameras
saw (common corner ids only), then refine intrinsics + E^sl jointly and keep that only if it is better
and well conditioned. Optionally (``scene_dir``) the rotation and translation direction of E^sl come from
SIFT matches on a textured scene instead, with the baseline length from the board or ``baseline``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from rigsfm.calibrate.board import (
    BoardDetector,
    BoardSpec,
    Detection,
    diagnose_no_detection,
    load_board_spec,
    read_gray,
    refuse_part_of_a_larger_chessboard,
)
from rigsfm.calibrate.dataset import RigFrames, discover_rigs
from rigsfm.calibrate.intrinsics import calibrate_camera
from rigsfm.calibrate.options import CalibrateOptions, Distortion
from rigsfm.calibrate.output import check_output, default_report_dir, write_outputs
from rigsfm.calibrate.report import check_report_dir
from rigsfm.calibrate.results import CalibrationResult, RigResult
from rigsfm.calibrate.scene import estimate_from_scene
from rigsfm.calibrate.stereo import calibrate_stereo
from rigsfm.core.conventions import rotation_angle_deg
from rigsfm.core.errors import InputError
from rigsfm.core.opencv_threads import one_opencv_thread
from rigsfm.core.rig import BASELINE_RANGE_M

logger = logging.getLogger(__name__)


def _detect(detector: BoardDetector, paths: dict[str, Path], where: str) -> tuple[dict[str, Detection | None], tuple[int, int]]:
    detections: dict[str, Detection | None] = {}
    sizes: dict[tuple[int, int], str] = {}
    for name, path in sorted(paths.items()):
        gray = read_gray(path)
        sizes.setdefault((gray.shape[1], gray.shape[0]), path.name)
        detections[name] = detector.detect(gray)
    if len(sizes) > 1:
        listing = ", ".join(f"{w}x{h} ({n})" for (w, h), n in sizes.items())
        raise InputError(f"{where}: images have different sizes ({listing}); one camera must have one image size")
    return detections, next(iter(sizes))


def calibrate_rig(frames: RigFrames, board: BoardSpec, *, distortion: Distortion = Distortion.AUTO, scene: RigFrames | None = None,
                  baseline: float | None = None) -> RigResult:
    detector = BoardDetector(board)
    detections, sizes = {}, {}
    for sensor in ("wide", "narrow"):
        where = f"rig {frames.name} {sensor}"
        paths = getattr(frames, sensor)
        detections[sensor], sizes[sensor] = _detect(detector, paths, where)
        found = sum(d is not None for d in detections[sensor].values())
        logger.info("%s: board found in %d of %d images", where, found, len(paths))
        if found == 0:
            raise diagnose_no_detection(board, [paths[n] for n in sorted(paths)], where)
        if board.type == "chessboard":
            refuse_part_of_a_larger_chessboard(
                board, [paths[n] for n, d in sorted(detections[sensor].items()) if d is not None], where)
    obj = board.object_points()
    wide = calibrate_camera("wide", detections["wide"], obj, sizes["wide"], distortion, f"rig {frames.name} wide")
    narrow = calibrate_camera("narrow", detections["narrow"], obj, sizes["narrow"], distortion, f"rig {frames.name} narrow")
    stereo = calibrate_stereo(wide, narrow, detections["wide"], detections["narrow"], obj, board.type == "chessboard",
                              f"rig {frames.name}")
    fit = stereo.final
    R, T = fit.R.copy(), fit.T.copy()
    result = RigResult(name=frames.name, wide=wide, narrow=narrow, stereo=stereo, R=R, T=T,
                       measured_baseline=baseline, warnings=wide.warnings + narrow.warnings)
    length = float(np.linalg.norm(T)) if baseline is None else float(baseline)
    if scene is not None:
        est = estimate_from_scene([(scene.wide[n], scene.narrow[n]) for n in scene.frames], fit.K_wide, fit.dist_wide,
                                  fit.K_narrow, fit.dist_narrow, f"rig {frames.name} scene")
        result.scene = est
        angle = rotation_angle_deg(est.R, R)
        cosine = float(np.clip(est.direction @ T / np.linalg.norm(T), -1, 1))
        result.R, result.T = est.R, est.direction * length
        result.notes.append(f"E^sl rotation and translation direction from the scene ({est.inliers} inliers); they differ "
                            f"from the board's by {angle:.3f} deg and {np.degrees(np.arccos(cosine)):.2f} deg; "
                            f"baseline length {length:.4f} m from {'--baseline' if baseline is not None else 'the board'}")
    elif baseline is not None:
        result.T = T / np.linalg.norm(T) * length
        result.notes.append(f"baseline rescaled from the board's {np.linalg.norm(T):.4f} m to the measured {length:.4f} m")
    return result


def check_baseline_option(baseline: float | None) -> None:
    """--baseline is a length in metres within the range `rigsfm run` accepts for E^sl in rigs.yaml."""
    if baseline is None:
        return
    if not (np.isfinite(baseline) and baseline > 0):
        raise InputError(f"--baseline must be a positive length in metres, got {baseline}")
    low, high = BASELINE_RANGE_M
    if not low <= baseline <= high:
        hint = f" (in millimetres? {baseline:g} mm is {baseline / 1000:g} m)" if baseline > high else ""
        raise InputError(f"--baseline {baseline:g} m is outside {low * 1000:g} mm - {high:g} m{hint}; give the "
                         "measured distance between the two cameras in metres")


def calibrate_rigs(board_dir: Path, board: BoardSpec, *, distortion: Distortion = Distortion.AUTO, scene_dir: Path | None = None,
                   baseline: float | None = None, rig_names: list[str] | None = None) -> CalibrationResult:
    """Calibrate every rig under ``board_dir`` (``<rig>/wide``, ``<rig>/narrow``)."""
    check_baseline_option(baseline)
    rigs = discover_rigs(Path(board_dir), "board images")
    if rig_names is not None:
        rigs = [r for r in rigs if r.name in rig_names]
    scenes: dict[str, RigFrames] = {}
    if scene_dir is not None:
        found = discover_rigs(Path(scene_dir), "scene images")
        scenes = {r.name: r for r in found}
        if len(found) == 1 and len(rigs) == 1:
            scenes = {rigs[0].name: found[0]}
        missing = [r.name for r in rigs if r.name not in scenes]
        if missing:
            raise InputError(f"scene images: no folder for rig(s) {', '.join(missing)} in {scene_dir} "
                             f"(expected {scene_dir}/<rig>/wide and {scene_dir}/<rig>/narrow)")
    # OpenCV's threads sum in a varying order, and the ill-conditioned narrow calibration amplifies that into the
    # narrow principal point: one thread makes the result reproducible bit for bit
    with one_opencv_thread():
        results = [calibrate_rig(r, board, distortion=distortion, scene=scenes.get(r.name), baseline=baseline)
                   for r in rigs]
    return CalibrationResult(board=board, rigs=results)


def write_calibration(result: CalibrationResult, out: Path, *, merge: bool = False, overwrite: bool = False,
                      report_dir: Path | None = None) -> tuple[Path, Path]:
    """Write rigs.yaml (merged into an existing one with ``merge``) and the report; returns both paths."""
    return write_outputs(result, Path(out), merge=merge, overwrite=overwrite, report_dir=report_dir)


def check_report_dir_outside_board(report_dir: Path, board_images: Path) -> None:
    """Refuse a report folder inside a board folder of rig folders: the next calibrate of it would take the
    report's folder for a rig (one rig's wide/ and narrow/ directly in BOARD ignore other folders)."""
    if (board_images / "wide").is_dir() or (board_images / "narrow").is_dir():
        return
    try:
        report_real, board_real = Path(report_dir).resolve(), board_images.resolve()
    except (OSError, RuntimeError):  # a link loop: the folders' own checks name it
        return
    if board_real == report_real or board_real in report_real.parents:
        raise InputError(f"the report folder {report_dir} lies inside the board image folder {board_images}, whose "
                         "every folder must be a rig (the next calibrate of it would take the report for one): "
                         "write rigs.yaml (--out) outside it, or give --report-dir a folder outside it")


def calibrate(board_images: Path, out: Path, options: CalibrateOptions) -> tuple[CalibrationResult, Path, Path]:
    """``rigsfm calibrate``: calibrate every rig under ``board_images`` and write rigs.yaml to ``out`` (checked
    before the slow part) and its report; returns the result, the rigs.yaml and the report folder."""
    spec = load_board_spec(options.board)
    check_baseline_option(options.baseline)
    names = [r.name for r in discover_rigs(board_images, "board images")]
    check_output(out, names, merge=options.merge, overwrite=options.overwrite)
    report_dir = options.report_dir if options.report_dir is not None else default_report_dir(Path(out))
    check_report_dir_outside_board(report_dir, Path(board_images))
    check_report_dir(report_dir, names, rigs_file=Path(out), overwrite=options.overwrite)
    result = calibrate_rigs(board_images, spec, distortion=options.distortion, scene_dir=options.scene_dir,
                            baseline=options.baseline)
    rigs_path, report = write_calibration(result, out, merge=options.merge, overwrite=options.overwrite,
                                          report_dir=options.report_dir)
    return result, rigs_path, report
