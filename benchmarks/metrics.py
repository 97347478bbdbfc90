"""Accuracy of one method's model against the rendered scene's ground truth (gauge-free, narrow cameras)."""

from __future__ import annotations

import numpy as np
import pycolmap
import scipy.stats

from rigsfm.synth.truth import compare_to_ground_truth

ERRORS = ("relative_rotation_deg", "translation_direction_deg", "distance_error_percent")


def similarity_aligned(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> pycolmap.Reconstruction | None:
    """A copy of ``estimate`` moved onto the truth by the similarity that best maps its registered
    camera centres (wide and narrow) onto the true ones; None with fewer than three."""
    names = [im.name for im in estimate.images.values() if im.has_pose]
    names = [n for n in names if truth.find_image_with_name(n) is not None]
    if len(names) < 3:
        return None
    est = np.array([estimate.find_image_with_name(n).projection_center() for n in names])
    gt = np.array([truth.find_image_with_name(n).projection_center() for n in names])
    gt_from_est = pycolmap.estimate_sim3d(est, gt)
    if gt_from_est is None:
        return None
    aligned = pycolmap.Reconstruction(estimate)
    aligned.transform(gt_from_est)
    return aligned


def evaluate(estimate: pycolmap.Reconstruction | None, truth: pycolmap.Reconstruction, *, metric: bool,
             align: bool = False) -> dict:
    """Narrow (and wide) errors; distances only when the model is metric or similarity-aligned."""
    total = sum(1 for im in truth.images.values() if im.name.split("/")[1] == "narrow")
    if estimate is None:
        return {"narrow": {"registered": 0, "total": total, "pairs": 0}, "wide": None, "aligned": align}
    scale_ok = metric
    if align:
        aligned = similarity_aligned(estimate, truth)
        scale_ok = aligned is not None
        estimate = aligned if aligned is not None else estimate
    narrow = compare_to_ground_truth(estimate, truth, "narrow")
    wide = compare_to_ground_truth(estimate, truth, "wide")
    if not scale_ok:
        for block in (narrow, wide):
            block["distance_error_percent"] = {"median": None, "max": None}
    return {"narrow": narrow, "wide": wide, "aligned": align}


def ratios_to_oracle(narrow: dict, oracle_narrow: dict) -> dict:
    """Each median and max error divided by the oracle's (None where either is missing or zero)."""
    ratios = {}
    for key in ERRORS:
        for stat in ("median", "max"):
            value = (narrow.get(key) or {}).get(stat)
            limit = (oracle_narrow.get(key) or {}).get(stat)
            ratios[f"{key}.{stat}"] = None if value is None or not limit else float(value / limit)
    return ratios


def roc_auc(score: np.ndarray, right: np.ndarray) -> float | None:
    """Area under the ROC curve (Mann-Whitney, ties at their average rank): the chance that a ``right`` item
    outscores a wrong one; None without both."""
    right = np.asarray(right, dtype=bool)
    pos, neg = int(right.sum()), int((~right).sum())
    if not pos or not neg:
        return None
    ranks = scipy.stats.rankdata(np.asarray(score, dtype=np.float64))
    return float((ranks[right].sum() - pos * (pos + 1) / 2) / (pos * neg))
