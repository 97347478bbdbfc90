"""Merge manual correspondences into the COLMAP database (after automatic matching, before mapping).

Per image, manual points are appended after the automatic keypoints with all-zero descriptor rows (so
they never win a descriptor match; a zero row also marks a keypoint as manual, which makes the merge
idempotent: a resumed or repeated run reuses the same rows, and manual matches from an earlier CSV are
dropped). Per pair: the manual correspondences are verified alone (calibrated RANSAC on the essential
matrix with the calibrated intrinsics), their inliers are united with the automatic matches, and the
union is verified again and replaces the pair's matches and two-view geometry.
"""

from __future__ import annotations

import contextlib
import logging
import sqlite3
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.geometry import PLANAR, POSED, Config, planar_fraction, sampson_error_px
from rigsfm.core.summary import ManualMatchesSummary, ManualPairSummary
from rigsfm.run.inputs.database import open_database
from rigsfm.run.matching.manual_matches import (
    MIN_CORRESPONDENCES,
    Correspondence,
    DegenerateCorrespondencesError,
    TooFewCorrespondencesError,
    check_spread,
)

logger = logging.getLogger(__name__)



@dataclass
class PairReport:
    image_a: str
    image_b: str
    given: int
    kept: int = 0  # manual correspondences among the pair's verified inliers after the merge
    automatic_inliers: int = 0  # the pair's verified automatic matches before the merge
    inliers_after: int = 0  # all verified matches of the pair after the merge
    config: str = ""
    rejected: list[dict] = field(default_factory=list)  # {line, xy_a, xy_b, epipolar_error_px}

    def as_dict(self) -> dict:
        return dict(self.__dict__)


MAX_H_INLIER_RATIO = 0.95  # as rigsfm.run.matching.extract: "planar" only if a homography explains nearly every inlier


def verification_options(max_error_px: float) -> pycolmap.TwoViewGeometryOptions:
    """Calibrated verification: the essential matrix always wins over the fundamental matrix (the
    intrinsics are calibrated), a homography only when it explains nearly every inlier."""
    options = pycolmap.TwoViewGeometryOptions()
    options.min_E_F_inlier_ratio = 0.0
    options.max_H_inlier_ratio = MAX_H_INLIER_RATIO
    options.ransac.max_error = max_error_px
    options.ransac.random_seed = 0
    options.ransac.min_num_trials = 200
    options.min_num_inliers = MIN_CORRESPONDENCES
    return options


def _zero_rows(descriptors: pycolmap.FeatureDescriptors) -> np.ndarray:
    data = np.asarray(descriptors.data)
    return np.flatnonzero(~data.any(axis=1)) if data.size else np.zeros(0, dtype=np.int64)


def append_manual_keypoints(
    database: pycolmap.Database, points: dict[int, list[tuple[float, float]]]
) -> dict[int, dict[tuple[float, float], int]]:
    """Keypoint index of every manual point per image id, appending the points not stored yet."""
    indices: dict[int, dict[tuple[float, float], int]] = {}
    new_rows: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for image_id, xys in points.items():
        keypoints = database.read_keypoints(image_id)
        descriptors = database.read_descriptors(image_id)
        if keypoints.shape[0] == 0:
            keypoints = np.zeros((0, 6), np.float32)
        existing = {(float(keypoints[i, 0]), float(keypoints[i, 1])): int(i) for i in _zero_rows(descriptors)}
        index: dict = {}
        added: list = []
        for xy in xys:
            key = (float(np.float32(xy[0])), float(np.float32(xy[1])))
            if key not in existing:
                existing[key] = keypoints.shape[0] + len(added)
                added.append([key[0], key[1], 1.0, 0.0, 0.0, 1.0][: keypoints.shape[1]])
            index[xy] = existing[key]
        indices[image_id] = index
        if added:
            new_rows[image_id] = (
                np.vstack([keypoints, np.asarray(added, np.float32)]),
                np.asarray(descriptors.data),
            )
    if not new_rows:
        return indices
    # COLMAP has no per-image descriptor update: rewrite every image's descriptors in one transaction.
    everything = {
        image.image_id: database.read_descriptors(image.image_id)
        for image in database.read_all_images()
        if database.exists_descriptors(image.image_id)
    }
    with pycolmap.DatabaseTransaction(database):
        database.clear_descriptors()
        for image_id, descriptors in everything.items():
            data = np.asarray(descriptors.data)
            if image_id in new_rows:
                keypoints, _ = new_rows[image_id]
                width = data.shape[1] if data.size else 128
                data = np.vstack(
                    [data.reshape(-1, width), np.zeros((keypoints.shape[0] - len(data), width), np.uint8)]
                )
                database.update_keypoints(image_id, keypoints)
            database.write_descriptors(image_id, pycolmap.FeatureDescriptors(descriptors.type, data))
    logger.info("Appended manual keypoints to %d image(s)", len(new_rows))
    return indices


def _automatic_inliers(geometry: pycolmap.TwoViewGeometry, manual1: set[int], manual2: set[int]) -> int:
    if geometry.config not in POSED:
        return 0
    return sum(
        m[0] not in manual1 and m[1] not in manual2 for m in np.asarray(geometry.inlier_matches).tolist()
    )


def _rows_in(matches: np.ndarray, geometry: pycolmap.TwoViewGeometry) -> np.ndarray:
    """Indices of the rows of ``matches`` that are among the geometry's inliers."""
    if geometry.config not in POSED:
        return np.zeros(0, dtype=np.int64)
    inliers = {tuple(m) for m in np.asarray(geometry.inlier_matches).tolist()}
    return np.array([i for i, m in enumerate(matches.tolist()) if tuple(m) in inliers], dtype=np.int64)


def _estimate(
    cam1: pycolmap.Camera,
    kp1: np.ndarray,
    cam2: pycolmap.Camera,
    kp2: np.ndarray,
    matches: np.ndarray,
    max_error_px: float,
) -> pycolmap.TwoViewGeometry:
    """COLMAP's calibrated two-view estimate, its inliers cut to a Sampson error under ``max_error_px``.

    COLMAP's RANSAC inlier set can hold matches 3-4x farther than its threshold from the epipolar lines
    of the E it returns (seen on 34 manual pairs of two rigs 170 degrees apart: two outliers at 11 and 17
    px kept, the pose 1 degree off); a pair this small cannot afford them.
    """
    options = verification_options(max_error_px)
    geometry = pycolmap.estimate_calibrated_two_view_geometry(cam1, kp1, cam2, kp2, matches, options)
    if geometry.config != Config.CALIBRATED or len(geometry.inlier_matches) == 0:
        return geometry
    inliers = np.asarray(geometry.inlier_matches)
    errors = sampson_error_px(geometry.E, cam1, cam2,  # type: ignore[arg-type]  # CALIBRATED: E is set
                              kp1[inliers[:, 0]], kp2[inliers[:, 1]])
    if np.all(errors <= max_error_px):
        return geometry
    refined = pycolmap.estimate_calibrated_two_view_geometry(
        cam1, kp1, cam2, kp2, inliers[errors <= max_error_px].astype(np.uint32), options
    )
    return refined if len(refined.inlier_matches) >= MIN_CORRESPONDENCES else geometry


def merge_pair(
    database: pycolmap.Database,
    ids: dict[str, int],
    pair: tuple[str, str],
    rows: Sequence[Correspondence],
    indices: dict[int, dict],
    max_error_px: float,
) -> PairReport:
    """Verify one pair's manual correspondences, unite them with its automatic matches, store the result."""
    a, b = pair
    swap = ids[a] > ids[b]  # COLMAP stores a pair with the smaller image id first
    id1, id2 = (ids[b], ids[a]) if swap else (ids[a], ids[b])
    xy1 = np.array([r.xy_b if swap else r.xy_a for r in rows])
    xy2 = np.array([r.xy_a if swap else r.xy_b for r in rows])
    manual = np.array([[indices[id1][tuple(p)], indices[id2][tuple(q)]] for p, q in zip(xy1, xy2)], np.uint32)
    cam1 = database.read_camera(database.read_image(id1).camera_id)
    cam2 = database.read_camera(database.read_image(id2).camera_id)
    kp1 = database.read_keypoints(id1)[:, :2].astype(np.float64)
    kp2 = database.read_keypoints(id2)[:, :2].astype(np.float64)
    report = PairReport(a, b, len(rows))
    manual_rows1 = set(_zero_rows(database.read_descriptors(id1)).tolist())
    manual_rows2 = set(_zero_rows(database.read_descriptors(id2)).tolist())
    has_geometry = database.exists_two_view_geometry(id1, id2)
    if has_geometry:
        report.automatic_inliers = _automatic_inliers(
            database.read_two_view_geometry(id1, id2), manual_rows1, manual_rows2
        )
    alone = _estimate(cam1, kp1, cam2, kp2, manual, max_error_px)
    alone_mask = np.isin(np.arange(len(rows)), _rows_in(manual, alone))
    if alone_mask.sum() >= 4 and report.automatic_inliers < MIN_CORRESPONDENCES:
        for name, xy, camera in (
            ((a, xy1, cam1), (b, xy2, cam2)) if not swap else ((b, xy1, cam1), (a, xy2, cam2))
        ):
            check_spread(
                xy[alone_mask],
                camera,
                f"the {alone_mask.sum()} consistent manual points of {a} <-> {b}",
                name,
            )
        fraction = planar_fraction(cam1, cam2, xy1[alone_mask], xy2[alone_mask], max_error_px)
        if alone.config in PLANAR or fraction >= MAX_H_INLIER_RATIO:
            raise DegenerateCorrespondencesError(
                f"manual correspondences {a} <-> {b}: one homography explains {100 * fraction:.0f} % of them (the "
                "points lie on one plane, or the two cameras share a centre), so the relative pose is ambiguous; "
                "add points off that plane (e.g. on walls, pillars and roofs as well as on the ground)"
            )
    raw = (
        database.read_matches(id1, id2) if database.exists_matches(id1, id2) else np.zeros((0, 2), np.uint32)
    )
    automatic = [m for m in raw.tolist() if m[0] not in manual_rows1 and m[1] not in manual_rows2]
    union = np.array(automatic + manual[alone_mask].tolist(), np.uint32).reshape(-1, 2)
    merged = _estimate(cam1, kp1, cam2, kp2, union, max_error_px)
    kept = np.isin(np.arange(len(rows)), _rows_in(manual, merged))
    report.kept, report.config = int(kept.sum()), Config(merged.config).name
    report.inliers_after = len(merged.inlier_matches) if merged.config in POSED else 0
    reference = merged if merged.config in POSED else alone
    errors = (
        sampson_error_px(reference.E, cam1, cam2, xy1, xy2)  # type: ignore[arg-type]  # POSED: E is set
        if reference.config in POSED
        else np.full(len(rows), np.nan)
    )
    report.rejected = [
        {
            "line": r.line,
            "xy_a": list(r.xy_a),
            "xy_b": list(r.xy_b),
            "epipolar_error_px": None if np.isnan(e) else round(float(e), 2),
        }
        for r, k, e in zip(rows, kept, errors)
        if not k
    ]
    if report.kept < MIN_CORRESPONDENCES and report.automatic_inliers < MIN_CORRESPONDENCES:
        lines = ", ".join(str(r["line"]) for r in report.rejected[:20])
        raise TooFewCorrespondencesError(
            f"only {report.kept} of {len(rows)} manual correspondences {a} <-> {b} agree on one relative pose "
            f"(calibrated RANSAC, {max_error_px:g} px); at least {MIN_CORRESPONDENCES} are needed. "
            f"Check or replace lines {lines} (rigsfm pick draws epipolar lines to help)"
        )
    with pycolmap.DatabaseTransaction(database):
        if database.exists_matches(id1, id2):
            database.delete_matches(id1, id2)
        database.write_matches(id1, id2, union)
        if has_geometry:
            database.delete_two_view_geometry(id1, id2)
        database.write_two_view_geometry(id1, id2, merged)
    logger.info(
        "Manual matches %s <-> %s: %d given, %d kept; %d -> %d verified matches",
        a,
        b,
        len(rows),
        report.kept,
        report.automatic_inliers,
        report.inliers_after,
    )
    return report


def add_manual_matches(
    database_path: Path, pairs: dict[tuple[str, str], list[Correspondence]], max_error_px: float = 4.0
) -> list[PairReport]:
    """Merge validated manual correspondences (see :func:`validate_manual_matches`) into the database."""
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        points: dict[int, list[tuple[float, float]]] = {}
        for (a, b), rows in pairs.items():
            points.setdefault(ids[a], []).extend(r.xy_a for r in rows)
            points.setdefault(ids[b], []).extend(r.xy_b for r in rows)
        indices = append_manual_keypoints(database, points)
        return [
            merge_pair(database, ids, pair, rows, indices, max_error_px)
            for pair, rows in sorted(pairs.items())
        ]


def drop_earlier_manual_matches(database_path: Path, pairs: Iterable[tuple[str, str]]) -> list[tuple[str, str]]:
    """Remove the matches and two-view geometry of every pair that holds manual matches of an earlier CSV and is
    not among ``pairs`` (this run's CSV, none without one), so that the matcher makes them again from the features
    alone: else a run without the CSV still registers from the clicks (:func:`merge_pair` replaces only the pairs
    it is given). Returns the pairs removed."""
    given = {frozenset(pair) for pair in pairs}
    dropped: list[tuple[str, str]] = []
    candidates = _images_ending_in_a_zero_row(database_path)
    if len(candidates) < 2:  # a pair needs manual rows in both images: nothing more to read
        return dropped
    with open_database(database_path) as database:
        names = {image.image_id: image.name for image in database.read_all_images()}
        manual = {image_id: set(_zero_rows(database.read_descriptors(image_id)).tolist())
                  for image_id in candidates if image_id in names and database.exists_descriptors(image_id)}
        ids = sorted(image_id for image_id, rows in manual.items() if rows)
        for i, id1 in enumerate(ids):
            for id2 in ids[i + 1:]:
                if frozenset((names[id1], names[id2])) in given or not database.exists_matches(id1, id2):
                    continue
                matches = database.read_matches(id1, id2)
                if not (np.isin(matches[:, 0], list(manual[id1])) | np.isin(matches[:, 1], list(manual[id2]))).any():
                    continue
                with pycolmap.DatabaseTransaction(database):
                    database.delete_matches(id1, id2)
                    if database.exists_two_view_geometry(id1, id2):
                        database.delete_two_view_geometry(id1, id2)
                dropped.append((names[id1], names[id2]))
    if dropped:
        logger.info("Manual matches of an earlier CSV removed from %d pair(s), matched again without them: %s",
                    len(dropped), ", ".join(f"{a} <-> {b}" for a, b in dropped))
    return dropped


def _images_ending_in_a_zero_row(database_path: Path) -> set[int]:
    """The ids of the images whose last descriptor row is all zero, read in SQLite one row per image: the only
    ones that can hold manual keypoints, as :func:`append_manual_keypoints` appends them after the automatic ones
    (reading every image's descriptors cost a pass over the whole table on each run)."""
    try:
        with contextlib.closing(sqlite3.connect(f"{Path(database_path).resolve().as_uri()}?mode=ro", uri=True)) as db:
            tails = db.execute("SELECT image_id, substr(data, length(data) - length(data) / rows + 1) FROM descriptors "
                               "WHERE rows > 0 AND length(data) > 0").fetchall()
    except sqlite3.OperationalError as error:  # as COLMAP's own errors: a full disk is named by disk_errors_named
        raise RuntimeError(f"{database_path}: {error}") from None
    return {int(image_id) for image_id, tail in tails if tail is not None and not any(tail)}


def manual_matches_summary(path: Path, reports: Sequence[PairReport]) -> ManualMatchesSummary:
    """The ``manual_matches`` entry of summary.json: per pair given / kept and the rejected lines."""
    return ManualMatchesSummary(file=str(path), given=sum(r.given for r in reports), kept=sum(r.kept for r in reports),
                                pairs=[ManualPairSummary(**r.as_dict()) for r in reports])
