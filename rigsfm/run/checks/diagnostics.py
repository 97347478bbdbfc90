"""Sanity checks of a finished reconstruction that a user cannot see in reprojection errors.

- Rigidity: with three or more rigs, the images fix the relative distances between rigs only through
  tracks seen by three or more rigs. Rigs linked to the rest by two-view tracks alone can slide along
  their viewing directions (a 4-rig circle 90 degrees apart is the classic case): the model still
  reprojects well while its shape is wrong.
- Weak links: when every match tying a rig to the others lies on one plane (one homography explains
  them, e.g. a single patch of wall or ground), the relative pose has two exact solutions and the mapper
  may pick the wrong one, degrees away, with perfect reprojection errors. Matches that fit a fundamental
  matrix but no essential matrix of the calibrated cameras are as suspect (a few matches, some wrong).
- Contradicted pairs: every verified image pair between rigs must agree with the model's poses. When the
  model contradicts most of a pair's matches, the mapper left that pair out (e.g. a loop of rigs that did
  not close) and the rigs on either side of it are placed by other, weaker links.
- Scale consistency: several scale measurements must agree within their uncertainties; when they do
  not, the shape of the model (or a measurement) is wrong.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.geometry import PLANAR, Config, sampson_error_px
from rigsfm.run.adjustment.scale import ScaleEstimate
from rigsfm.run.inputs.database import open_database
from rigsfm.run.mapping.ties import loosely_tied_rigs, rig_groups, rig_of

MAX_NORMALISED_RESIDUAL = 5.0
# The extent of a metric network beyond which a length in scale.yaml was surely given in another unit: rigs that
# overlap on one scene stand metres to kilometres apart, never millimetres or tens of kilometres.
PLAUSIBLE_SPAN_M = (0.2, 20_000.0)


WEAK = {**dict.fromkeys(PLANAR, "on one plane"),
        Config.UNCALIBRATED: "fitting no essential matrix of the calibrated cameras"}
MIN_PAIR_INLIERS = 15  # verified matches that make an image pair a link between two rigs


def _pairs_between_rigs(db: pycolmap.Database, reconstruction: pycolmap.Reconstruction):
    """Verified image pairs between registered images of two different rigs with at least
    ``MIN_PAIR_INLIERS`` inliers, as ``(database id 1, image 1, database id 2, image 2, geometry)``."""
    registered = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    names = {image.image_id: image.name for image in db.read_all_images()}
    for pair_id, geometry in zip(*db.read_two_view_geometries()):
        id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
        image1, image2 = registered.get(names[id1]), registered.get(names[id2])
        if (image1 is not None and image2 is not None and rig_of(image1) != rig_of(image2)
                and len(geometry.inlier_matches) >= MIN_PAIR_INLIERS):
            yield id1, image1, id2, image2, geometry


def weakly_tied_rigs(database_path: Path, reconstruction: pycolmap.Reconstruction) -> dict[str, list[str]]:
    """Registered rigs tied to the largest group of rigs only through weak image pairs (planar, or not
    consistent with the calibration), each with those pairs (``"rig01-rig02: 68 matches on one plane"``);
    empty when every rig has a sound link."""
    rigs = sorted({rig_of(image) for image in reconstruction.images.values() if image.has_pose})
    if len(rigs) < 2:
        return {}
    sound: list = []
    weak: dict = {}
    with open_database(database_path) as db:
        for _, image1, _, image2, geometry in _pairs_between_rigs(db, reconstruction):
            a, b = rig_of(image1), rig_of(image2)
            if geometry.config in WEAK:
                row = f"{min(a, b)}-{max(a, b)}: {len(geometry.inlier_matches)} matches {WEAK[geometry.config]}"
                weak.setdefault(a, []).append(row)
                weak.setdefault(b, []).append(row)
            else:
                sound.append((a, b))
    largest = max(rig_groups(rigs, sound), key=len)
    core = largest if len(largest) > 1 else []
    return {rig: sorted(set(weak[rig])) for rig in rigs if rig not in core and rig in weak}


# Median epipolar error of a verified pair above which the model contradicts it. Correct models with
# realistic calibration errors stay under 5 px on rigs far apart; the wrong shapes seen stood at 30-370 px.
MAX_PAIR_ERROR_PX = 10.0


def contradicted_pairs(database_path: Path, reconstruction: pycolmap.Reconstruction) -> list[str]:
    """Verified image pairs between registered rigs whose matches the model's poses contradict (median
    epipolar error above ``MAX_PAIR_ERROR_PX``), as ``"rig01-rig04: 620 matches, median error 348.5 px"``.

    Pairs verified as calibrated or planar are checked: their matches are true correspondences, which
    satisfy the epipolar constraint of correct poses. Uncalibrated pairs (no essential matrix fits) are not.
    """
    rows = []
    with open_database(database_path) as db:
        for id1, image1, id2, image2, geometry in _pairs_between_rigs(db, reconstruction):
            if geometry.config not in (Config.CALIBRATED, *PLANAR):
                continue
            matches = geometry.inlier_matches
            two_from_one = image2.cam_from_world() * image1.cam_from_world().inverse()
            errors = sampson_error_px(np.asarray(pycolmap.essential_matrix_from_pose(two_from_one)),
                                      image1.camera, image2.camera,
                                      db.read_keypoints(id1)[matches[:, 0], :2], db.read_keypoints(id2)[matches[:, 1], :2])
            median = float(np.median(errors))
            if median > MAX_PAIR_ERROR_PX:
                a, b = sorted((rig_of(image1), rig_of(image2)))
                rows.append(f"{a}-{b}: {len(matches)} matches, median error {median:.1f} px")
    return sorted(rows)


def implausible_span(reconstruction: pycolmap.Reconstruction) -> str | None:
    """A warning where the registered cameras of a metrically scaled model span (the diagonal of the box round their
    centres: linear in the images, and at most sqrt(3) times their farthest pair, enough for an order of magnitude's
    test) less or more than any network of rigs does (:data:`PLAUSIBLE_SPAN_M`); None otherwise."""
    centres = np.array([image.projection_center() for image in reconstruction.images.values() if image.has_pose])
    if len(centres) < 2:
        return None
    span = float(np.linalg.norm(centres.max(axis=0) - centres.min(axis=0)))
    low, high = PLAUSIBLE_SPAN_M
    if low <= span <= high:
        return None
    shown = f"{span / 1000:.3g} km" if span > high else f"{span * 1000:.3g} mm"
    return (f"IMPLAUSIBLE SCALE: the registered cameras span {shown}, where a network of rigs spans {low:g} m to "
            f"{high / 1000:g} km: is a length in scale.yaml in another unit (centimetres or millimetres for metres)?")


def check_reconstruction(reconstruction: pycolmap.Reconstruction, scale: ScaleEstimate | None,
                         database_path: Path | None = None) -> list[str]:
    """Warnings (empty when the checks pass); the checks of image pairs need the workspace's database."""
    warnings = []
    weak = weakly_tied_rigs(database_path, reconstruction) if database_path is not None else {}
    if weak:
        pairs = sorted({pair for rows in weak.values() for pair in rows})
        warnings.append(
            f"POSE AMBIGUOUS: {', '.join(weak)} are tied to the other rigs only by weak matches ({'; '.join(pairs)}); "
            "matches on one plane allow two exact poses, matches that fit no essential matrix include wrong ones, and "
            "the pose may be degrees off. Add correspondences off that plane (--manual-matches, e.g. on pillars, "
            "stands and the ground), try --features asift, or add a rig in between"
        )
    contradicted = contradicted_pairs(database_path, reconstruction) if database_path is not None else []
    if contradicted:
        warnings.append(
            f"MATCHES CONTRADICT THE MODEL: {'; '.join(contradicted)}. Either the model is wrong around these "
            "rigs (the mapper left these verified matches out, e.g. a loop of rigs that did not close) or the "
            "matches are false (repeated texture); check these rigs against scale.yaml measurements, try the "
            "other --mapper, or add rigs in between"
        )
    loose = loosely_tied_rigs(reconstruction)
    if loose:
        warnings.append(
            f"SHAPE NOT DETERMINED: {', '.join(loose)} share no points with two other rigs, so their distances "
            "to the rest are not fixed by the images and may be wrong; add rigs in between or wider views, "
            "and check against scale.yaml measurements"
        )
    implausible = implausible_span(reconstruction) if scale is not None else None
    if implausible:
        warnings.append(implausible)
    for unused in scale.unused if scale is not None else ():
        warnings.append(f"SCALE MEASUREMENT UNUSED: {unused}; the scale rests on the other measurements")
    if scale is not None and len(scale.measurements) > 1:
        for row in scale.residuals():
            if abs(row["residual_meters"]) > MAX_NORMALISED_RESIDUAL * row["sigma_meters"]:
                warnings.append(
                    f"SCALE MEASUREMENTS DISAGREE: {row['label']} is {row['reconstructed_meters']:.4f} m in the model "
                    f"but measured {row['meters']:.4f} m ({row['residual_percent']:+.2f} %, more than "
                    f"{MAX_NORMALISED_RESIDUAL:g} sigma); the model's shape or that measurement is wrong"
                )
    return warnings
