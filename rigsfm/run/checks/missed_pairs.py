"""Stage 10, check_pairs: the image pairs the first pass skipped that the model says would have shared many points."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pycolmap

from rigsfm.core.geometry import project_world
from rigsfm.core.names import ImageName
from rigsfm.core.summary import MissedPairSummary, PairsSummary
from rigsfm.run.matching.pairs import PairSelection
from rigsfm.run.options import Pairs

MISSED_MIN_POINTS = 50  # a skipped pair predicted to share fewer points is not worth a warning
# A skipped pair is missed when it beats the weakest matched pair of both its images by this factor: the
# predicted count is a small multiple of a pair's verified inliers, so a smaller margin flags the first pass's
# ordinary near-ties at the k-th partner.
MISSED_FACTOR = 2.0
MISSED_MAX_VIEW_ANGLE_DEG = 40.0  # SIFT rarely matches a point seen from directions further apart


@dataclass(frozen=True)
class MissedPair:
    image_a: str
    image_b: str
    predicted_points: int  # model points seen by one image that the other sees from a similar direction
    weakest_matched: int  # the same count for the weakest pair matched for either image


def _observed_points(reconstruction: pycolmap.Reconstruction, image: pycolmap.Image) -> np.ndarray:
    ids = [p.point3D_id for p in image.get_observation_points2D()]
    return np.array([reconstruction.point3D(i).xyz for i in ids]).reshape(-1, 3)


def covisible_points(reconstruction: pycolmap.Reconstruction, pairs: Sequence[tuple[str, str]]) -> list[int]:
    """Per pair of registered image names: the points of the model observed in one image that the other sees
    (in front, inside its image, from a viewing direction within ``MISSED_MAX_VIEW_ANGLE_DEG`` of the observing
    image's), the larger of the two counts. Batched per observing image: a 64-rig circle asks for ~8 000 pairs."""
    images = {im.name: im for im in reconstruction.images.values() if im.has_pose}
    partners: dict[str, list[str]] = {}
    for a, b in pairs:
        partners.setdefault(a, []).append(b)
        partners.setdefault(b, []).append(a)
    cos_max = np.cos(np.radians(MISSED_MAX_VIEW_ANGLE_DEG))
    seen_from: dict[tuple[str, str], int] = {}  # (observing image, other image) -> count
    for name, others in partners.items():
        xyz = _observed_points(reconstruction, images[name])
        ray = xyz - images[name].projection_center()
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        to_points = xyz[None] - np.array([images[o].projection_center() for o in others])[:, None]  # (M, N, 3)
        cosine = np.einsum("nk,mnk->mn", ray, to_points) / np.linalg.norm(to_points, axis=2)
        for other, close in zip(others, cosine > cos_max):
            count = 0
            if close.any():  # (most pairs of a large circle: no point within the angle)
                camera = reconstruction.cameras[images[other].camera_id]
                count = int(np.sum(project_world(camera, images[other].cam_from_world(), xyz[close])[1]))
            seen_from[(name, other)] = count
    return [max(seen_from[(a, b)], seen_from[(b, a)]) for a, b in pairs]


def missed_pairs(reconstruction: pycolmap.Reconstruction, selection: PairSelection) -> list[MissedPair]:
    """Skipped pairs of registered images that the final model says would have shared many points: at least
    ``MISSED_MIN_POINTS`` and ``MISSED_FACTOR`` x the weakest pair matched for each of its images with a partner
    of the same sensor (by the same count, :func:`covisible_points`; matched pairs under ``MISSED_MIN_POINTS``
    do not count). Pairs of a wide and a narrow image of two
    rigs are not checked: the shared points the model predicts say nothing of a 4x change of scale."""
    if selection.mode != Pairs.AUTO or not selection.skipped:
        return []
    posed = {im.name: im for im in reconstruction.images.values() if im.has_pose}
    matched = [(a, b) for a, b in selection.pairs if a in posed and b in posed
               and ImageName.parse(a).rig != ImageName.parse(b).rig]
    sensor = {name: ImageName.parse(name).sensor for name in posed}
    # Wide and narrow images of two rigs are 4x the scale apart: SIFT rarely matches them, and the first pass
    # found too few matches (MIN_NARROW_SCORE); their skipped pairs are not checked.
    skipped = [(a, b) for a, b in selection.skipped if a in posed and b in posed and sensor[a] == sensor[b]
               and ImageName.parse(a).rig != ImageName.parse(b).rig]
    counts = covisible_points(reconstruction, matched + skipped)
    weakest: dict[tuple[str, str], int] = {}  # (image, sensor of the partner) -> weakest matched pair's count
    for (a, b), shared in zip(matched, counts):
        if shared < MISSED_MIN_POINTS:  # matched but sharing nothing in the model: no measure of the cut
            continue
        for one, other in ((a, b), (b, a)):
            key = (one, sensor[other])
            weakest[key] = min(weakest.get(key, shared), shared)
    missed = []
    for (a, b), shared in zip(skipped, counts[len(matched):]):
        bar = max(weakest.get((a, sensor[b]), 0), weakest.get((b, sensor[a]), 0))
        if shared >= MISSED_MIN_POINTS and shared > MISSED_FACTOR * bar:
            missed.append(MissedPair(a, b, shared, bar))
    return sorted(missed, key=lambda m: -m.predicted_points)


def pairs_report(reconstruction: pycolmap.Reconstruction, selection: PairSelection) -> tuple[PairsSummary, str | None]:
    """summary.json's ``pairs`` (counts, first-pass time, missed pairs) and a warning when pairs were missed."""
    missed = missed_pairs(reconstruction, selection)
    report = PairsSummary(**selection.summary(), missed=[MissedPairSummary(**vars(m)) for m in missed[:20]],
                          num_missed=len(missed))
    if not missed:
        return report, None
    worst = missed[0]
    return report, (f"PAIRS MISSED: {len(missed)} skipped image pair(s) would have shared points by the final model "
                    f"(e.g. {worst.image_a} - {worst.image_b}: ~{worst.predicted_points} points, more than the "
                    f"weakest matched pair's {worst.weakest_matched}); re-run with --pairs exhaustive or a larger "
                    f"--neighbours")
