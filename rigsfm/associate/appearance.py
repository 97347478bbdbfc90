"""An appearance cue for association: the grey of each detection's head and of the torso below it.

Two detections of one person look alike across views (hair, clothes) where two persons along one epipolar line
mostly do not. Per detection a small descriptor is sampled from its narrow image: the mean grey of a box on the head
and of a box on the torso below it, each sized by the head's apparent size in that view (a head of ~0.11 m radius at
the view's typical depth of its persons), and each divided by the image's median grey (the exposure differs per
image) and taken as a log. The likelihood ratio of "same person" against "different persons" for two descriptors'
difference is estimated from the frame itself, never from a truth: the differences within the confident groups of a
first association (with a share of outliers: an occluded torso, a wrong member) against those of random pairs of
detections in different views.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigsfm.core.image_files import read_image

logger = logging.getLogger(__name__)

HEAD_RADIUS_M = 0.11  # a head's radius, what sets each view's box size
TORSO_BELOW_M = 0.40  # the torso's centre below the head's centre
MIN_PAIRS = 30  # same-person pairs needed to estimate the model from
OUTLIER_SHARE = 0.1  # of same-person pairs that look like different persons (occlusion, wrong members)
MAX_PAIRS_RANDOM = 20000


def read_grey(path: Path) -> np.ndarray | None:
    """The image's greys (its pixels as stored, whole numbers, as every reader of rigsfm's), or None where it cannot
    be read (the cue is then left out)."""
    import cv2

    return read_image(path, cv2.IMREAD_GRAYSCALE)


def _box_means(grey: np.ndarray, centres: np.ndarray, half: float) -> np.ndarray:
    """The mean grey of the box of half-width ``half`` around each of ``centres``, cut to the image: each box summed
    where it lies (a few hundred small boxes: less than numpy's integral image of the whole frame), or for stored
    8-bit greys (an image file's) by OpenCV's integral image: whole numbers, the same sums to the bit."""
    h, w = grey.shape
    x0 = np.clip(np.round(centres[:, 0] - half), 0, w - 1).astype(np.int64)
    x1 = np.clip(np.round(centres[:, 0] + half) + 1, 1, w).astype(np.int64)
    y0 = np.clip(np.round(centres[:, 1] - half), 0, h - 1).astype(np.int64)
    y1 = np.clip(np.round(centres[:, 1] + half) + 1, 1, h).astype(np.int64)
    x1, y1 = np.maximum(x1, x0 + 1), np.maximum(y1, y0 + 1)
    if grey.dtype == np.uint8 and grey.ndim == 2 and grey.size:
        import cv2

        # OpenCV's summed-area table (one pass in C over the frame, a fraction of a millisecond): the sums of
        # whole-number greys as float64s, exact, so the same as each box summed by itself
        table = cv2.integral(grey, sdepth=cv2.CV_64F)
        total = table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]
    else:  # greys that may hold fractions: numpy's own sum of each box, whose order of adding sets the last bits
        total = np.array([grey[a:b, c:d].sum() for a, b, c, d in zip(y0.tolist(), y1.tolist(), x0.tolist(),
                                                                      x1.tolist())], dtype=np.float64)
    return total / ((x1 - x0) * (y1 - y0))


def median_grey(grey: np.ndarray) -> float:
    """``np.median`` of an image's greys: by their counts where they are whole numbers 0-65535 (an image file's,
    as read_grey gives them), a fraction of a sort's or a partition's time over the whole frame; else np.median."""
    flat = grey.ravel()
    if flat.dtype in (np.uint8, np.uint16):
        whole = flat
    else:
        with np.errstate(invalid="ignore"):  # a NaN or an out-of-range grey casts to anything: the test fails it
            whole = flat.astype(np.uint16)
        if not np.array_equal(whole, flat):  # anything else (a fraction, a NaN, out of range): no counts
            return float(np.median(grey))
    if not flat.size:
        return float(np.median(grey))
    below = np.cumsum(_counts(whole))  # below[g]: how many greys are at most g
    n = len(flat)
    low = int(np.searchsorted(below, (n - 1) // 2, side="right"))  # the middle one (n odd) or two (n even)
    high = int(np.searchsorted(below, n // 2, side="right"))
    return (low + high) / 2


def _counts(whole: np.ndarray) -> np.ndarray:
    """``np.bincount`` of whole-number greys; 8-bit ones by OpenCV's histogram (a fraction of bincount's time, which
    widens every grey to a 64-bit index first), whose float32 counts are whole numbers, exact below 2^24 pixels."""
    if whole.dtype != np.uint8 or not 0 < len(whole) < 2 ** 24:
        return np.bincount(whole)
    import cv2

    return cv2.calcHist([whole], [0], None, [256], [0, 256]).ravel().astype(np.int64)


def describe(grey: np.ndarray, xy: np.ndarray, head_px: float) -> np.ndarray:
    """N x 2 descriptors (log head and torso grey over the image's median) of detections ``xy`` (raw pixels), the
    head's apparent radius being ``head_px``; the torso lies below the head in the image (upright cameras)."""
    if not len(xy):
        return np.zeros((0, 2))
    median = max(median_grey(grey), 1.0)
    head = _box_means(grey, xy, max(0.5 * head_px, 1.0))
    below = xy + np.array([0.0, head_px * TORSO_BELOW_M / HEAD_RADIUS_M])
    torso = _box_means(grey, below, max(0.8 * head_px, 1.0))
    return np.log(np.maximum(np.c_[head, torso], 1.0) / median)


@dataclass(frozen=True)
class AppearanceModel:
    """Per dimension the spread of same-person and of different-person differences (zero-mean normals), and the
    same-person pairs' outlier share."""

    same_sigma: np.ndarray
    different_sigma: np.ndarray
    outliers: float = OUTLIER_SHARE
    pairs: int = 0  # same-person pairs it was estimated from

    def log_ratio(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """log p(a - b | same) / p(a - b | different) for rows of descriptors; 0 where either is missing."""
        d = a - b
        same = np.sum(-np.log(self.same_sigma) - 0.5 * (d / self.same_sigma) ** 2, axis=-1)
        different = np.sum(-np.log(self.different_sigma) - 0.5 * (d / self.different_sigma) ** 2, axis=-1)
        ratio = np.log((1.0 - self.outliers) * np.exp(np.clip(same - different, -50, 50)) + self.outliers)
        return np.where(np.isfinite(ratio), ratio, 0.0)

    def group_log_ratio(self, descriptors: np.ndarray, members: np.ndarray) -> np.ndarray:
        """Per group (members G x V into the stacked ``descriptors``), the pairs' log ratios summed and weighted by
        2 / members: a group of m holds m - 1 independent differences, not m (m - 1) / 2."""
        present = members >= 0
        views = members.shape[1]
        none = np.zeros(0, dtype=np.int64)
        rows, first, second = [none], [none], [none]
        for a in range(views):
            for b in range(a + 1, views):
                both = np.flatnonzero(present[:, a] & present[:, b])
                rows.append(both)
                first.append(members[both, a])
                second.append(members[both, b])
        # every pair's ratio in one call, summed per group in the order of the pairs of views (bincount adds its
        # weights in their order, as a sum pair by pair would)
        ratio = self.log_ratio(descriptors[np.concatenate(first)], descriptors[np.concatenate(second)])
        total = np.bincount(np.concatenate(rows), weights=ratio, minlength=len(members)).astype(np.float64)
        count = present.sum(axis=1)
        return total * 2.0 / np.maximum(count, 2)


def _robust_sigma(d: np.ndarray) -> np.ndarray:
    return np.maximum(1.4826 * np.median(np.abs(d), axis=0), 1e-3)


def estimate(descriptors: np.ndarray, view_of: np.ndarray, groups: np.ndarray,
             seed: int = 0) -> AppearanceModel | None:
    """The model from the confident ``groups`` (G x V member rows) against random pairs of detections in different
    views; None where the groups hold too few pairs."""
    same = []
    views = groups.shape[1]
    for a in range(views):
        for b in range(a + 1, views):
            both = (groups[:, a] >= 0) & (groups[:, b] >= 0)
            same.append(descriptors[groups[both, a]] - descriptors[groups[both, b]])
    same_d = np.concatenate(same) if same else np.zeros((0, descriptors.shape[1]))
    same_d = same_d[np.all(np.isfinite(same_d), axis=1)]
    if len(same_d) < MIN_PAIRS:
        return None
    rng = np.random.default_rng(seed)
    n = len(descriptors)
    first, second = rng.integers(0, n, MAX_PAIRS_RANDOM), rng.integers(0, n, MAX_PAIRS_RANDOM)
    keep = view_of[first] != view_of[second]
    random_d = descriptors[first[keep]] - descriptors[second[keep]]
    random_d = random_d[np.all(np.isfinite(random_d), axis=1)]
    if len(random_d) < MIN_PAIRS:
        return None
    same_sigma = _robust_sigma(same_d)
    # random pairs are different persons bar a few; their spread is the plain one (no outliers to resist)
    different_sigma = np.maximum(np.sqrt(np.mean(random_d ** 2, axis=0)), same_sigma)
    logger.info("appearance: same-person spread %s, different %s (%d pairs)", np.round(same_sigma, 3),
                np.round(different_sigma, 3), len(same_d))
    return AppearanceModel(same_sigma, different_sigma, OUTLIER_SHARE, len(same_d))


def head_radius_px(focal: float, depth_m: float) -> float:
    return focal * HEAD_RADIUS_M / max(depth_m, 1e-3) if math.isfinite(depth_m) else float("nan")
