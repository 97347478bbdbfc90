"""Flags and verdicts on a rig's series of pose changes: stable, shaking or moved.

Every registered frame carries its change from the baseline as a 6-vector ``[w, d]`` (``w``: rotation
vector in radians with ``R_frame = exp(w) R_baseline``; ``d``: centre shift in metres in the baseline
camera frame) and its covariance. A single wide camera whose map points lie at similar depths (e.g. the
stands of an arena) cannot tell a sideways shift from a small rotation well (centimetres of shift can hide
in a hundredth of a degree), so "moved more than the threshold" is only claimed when that part of the
change (rotation or shift) is also significant on its own: chi-square of the part with its marginal
covariance > ``significance_chi2``.

- A frame is *flagged* if its rotation exceeds ``rotation_deg`` or its shift exceeds ``translation_mm``
  and that part is significant.
- A *step* is a split of the series (binary segmentation) where, in rotation or in shift, the component-
  wise median after the split differs from the level before it (the median of the frames before, or the
  baseline for a step at the first frame: moved before tracking started) by more than the threshold,
  significantly, by ``step_to_spread`` times the frames' median spread about their levels (so zero-mean
  shake is not a step), and persists: ``min_persist_frames`` frames after it and, before it, as many or the
  baseline's level (a step after the first frames of the series, all within the thresholds of the baseline),
  ``persist_fraction`` of them closer to their own level than to the other.
- Verdict: ``moved`` if there is a step, else ``shaking`` if any frame is flagged (zero-mean jitter),
  else ``stable``; ``no data`` without registered frames.
- *Unsettled* frames: the series' last frames, all flagged after frames that were not, and fewer than
  ``min_persist_frames``: a rig moved just now, which reads ``shaking`` until enough frames follow its step, or a
  shake; the next frames tell which. Flags are against the baseline, so after a step (whose frames are all
  flagged) none are unsettled: a second move shows as its own step.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field

import numpy as np

from rigsfm.track.options import Thresholds


@dataclass(frozen=True)
class Step:
    index: int  # first frame (position in the registered series) at the new level
    frame: str
    rotation_deg: float
    translation_mm: float
    chi2: float


@dataclass
class Verdict:
    verdict: str
    steps: list[Step] = field(default_factory=list)
    flagged: list[bool] = field(default_factory=list)
    jitter_rotation_deg: float | None = None  # RMS about the piecewise-constant levels
    jitter_translation_mm: float | None = None
    unsettled_frames: int = 0  # the last frames off after still ones, too few yet to call a step (module docstring)

    def to_dict(self) -> dict:
        data = asdict(self)
        data["flagged_frames"] = int(sum(self.flagged))
        del data["flagged"]
        return data


PARTS = (slice(0, 3), slice(3, 6))  # rotation (rad), translation (m)
SCALES = (np.degrees(1.0), 1000.0)  # to degrees, millimetres


def magnitudes(change: np.ndarray) -> tuple[float, float]:
    """(rotation in degrees, shift in millimetres) of a 6-vector change."""
    return float(np.degrees(np.linalg.norm(change[:3]))), float(1000.0 * np.linalg.norm(change[3:]))


def _limits(thresholds: Thresholds) -> tuple[float, float]:
    return thresholds.rotation_deg, thresholds.translation_mm


def chi2(change: np.ndarray, covariance: np.ndarray) -> float:
    return float(change @ np.linalg.pinv(covariance) @ change)


def significant_parts(change: np.ndarray, covariance: np.ndarray, thresholds: Thresholds) -> list[int]:
    """Parts (0 rotation, 1 translation) of a change above their threshold and significant on their own
    (chi-square of that part with its marginal covariance, which holds the rotation/shift coupling)."""
    parts = []
    for p, (part, scale, limit) in enumerate(zip(PARTS, SCALES, _limits(thresholds))):
        value = change[part]
        if scale * np.linalg.norm(value) > limit and chi2(value, covariance[part, part]) > thresholds.significance_chi2:
            parts.append(p)
    return parts


def flag_frames(changes: np.ndarray, covariances: np.ndarray, baseline_covariance: np.ndarray,
                thresholds: Thresholds) -> list[bool]:
    return [bool(significant_parts(c, s + baseline_covariance, thresholds)) for c, s in zip(changes, covariances)]


def _distance(values: np.ndarray, level: np.ndarray, p: int) -> np.ndarray:
    return SCALES[p] * np.linalg.norm(values[:, PARTS[p]] - level[PARTS[p]], axis=1)


def _at_level(changes: np.ndarray, level: np.ndarray, thresholds: Thresholds) -> bool:
    """Every change within the rotation and shift thresholds of ``level``."""
    return all(bool(np.all(_distance(changes, level, p) <= limit)) for p, limit in enumerate(_limits(thresholds)))


def _step_score(changes, lo, k, hi, pre, pre_cov, post, post_cov, thresholds) -> float | None:
    """Normalised size of the step at ``k`` if it is a valid step (see the module docstring), else None."""
    step = post - pre
    best = None
    for p in significant_parts(step, pre_cov + post_cov, thresholds):
        size = SCALES[p] * np.linalg.norm(step[PARTS[p]])
        after, before = changes[k:hi], changes[lo:k]
        spread = float(np.median(_distance(after, post, p)))
        if len(before):
            spread = max(spread, float(np.median(_distance(before, pre, p))))
        if size < thresholds.step_to_spread * spread:
            continue
        persists = np.mean(_distance(after, post, p) < _distance(after, pre, p)) >= thresholds.persist_fraction
        if len(before):
            persists &= np.mean(_distance(before, pre, p) < _distance(before, post, p)) >= thresholds.persist_fraction
        if persists:
            best = max(best or 0.0, size / _limits(thresholds)[p])
    return best  # type: ignore[return-value]  # numpy's float64 is a float


def _segment(changes, covariances, lo, hi, level, level_cov, thresholds, frames) -> list[Step]:
    """Steps within changes[lo:hi] given the level (and its covariance) before ``lo`` (None: unknown)."""
    m = thresholds.min_persist_frames
    best = None
    for k in range(lo, hi - m + 1):
        # the baseline's known level (the reference map) stands for frames the series lacks before a split whose
        # frames before all lie within the thresholds of it: a bump after one or two still frames is a step
        if k == lo and level is None or 0 < k - lo < m and (level is None or not _at_level(changes[lo:k], level,
                                                                                               thresholds)):
            continue
        post = np.median(changes[k:hi], axis=0)
        post_cov = np.pi / 2 * covariances[k:hi].mean(axis=0) / (hi - k)
        if k == lo or k - lo < m:  # the frames before are at the baseline's level (checked above)
            pre, pre_cov = level, level_cov
        else:
            pre = np.median(changes[lo:k], axis=0)
            pre_cov = np.pi / 2 * covariances[lo:k].mean(axis=0) / (k - lo)
        if _step_score(changes, lo, k, hi, pre, pre_cov, post, post_cov, thresholds) is None:
            continue
        # Among valid splits, the one that fits the frames best (least absolute deviation from the levels).
        cost = sum(float(np.sum(_distance(changes[a:b], level_, p))) / _limits(thresholds)[p]
                   for a, b, level_ in ((lo, k, pre), (k, hi, post)) for p in (0, 1))
        if best is None or cost < best[0]:
            best = (cost, k, post - pre, chi2(post - pre, pre_cov + post_cov))
    if best is None:
        return []
    _, k, step, significance = best
    rotation, translation = magnitudes(step)
    found = Step(k, frames[k], rotation, translation, significance)
    left = _segment(changes, covariances, lo, k, level, level_cov, thresholds, frames) if k > lo else []
    right = _segment(changes, covariances, k, hi, None, None, thresholds, frames)
    return [*left, found, *right]


def classify(frames: list[str], changes: np.ndarray | list, covariances: np.ndarray | list,
             baseline_covariance: np.ndarray, thresholds: Thresholds | None = None) -> Verdict:
    """Verdict of one rig from its registered frames (in time order), see the module docstring."""
    thresholds = thresholds or Thresholds()
    changes = np.asarray(changes, dtype=np.float64).reshape(-1, 6)
    covariances = np.asarray(covariances, dtype=np.float64).reshape(-1, 6, 6)
    if len(changes) == 0:
        return Verdict("no data")
    flagged = flag_frames(changes, covariances, baseline_covariance, thresholds)
    steps = _segment(changes, covariances, 0, len(changes), np.zeros(6), baseline_covariance, thresholds, frames)
    bounds = [0, *[s.index for s in steps], len(changes)]
    residuals = np.concatenate([changes[a:b] - np.median(changes[a:b], axis=0)
                                for a, b in itertools.pairwise(bounds) if b > a])
    rotation = np.degrees(np.linalg.norm(residuals[:, :3], axis=1))
    translation = 1000.0 * np.linalg.norm(residuals[:, 3:], axis=1)
    verdict = "moved" if steps else "shaking" if any(flagged) else "stable"
    return Verdict(verdict, steps, flagged, float(np.sqrt(np.mean(rotation**2))),
                   float(np.sqrt(np.mean(translation**2))), _unsettled(flagged, steps, thresholds))


def _unsettled(flagged: list[bool], steps: list[Step], thresholds: Thresholds) -> int:
    """How many of the last frames are flagged after unflagged ones, where fewer than a step needs after it (else
    0): a shaking rig's flags come and go, a rig moved just now has its flags at the end."""
    n = len(flagged)
    trailing = next((k for k in range(n) if not flagged[n - 1 - k]), n)
    if steps or not 0 < trailing < thresholds.min_persist_frames or any(flagged[:n - trailing]):
        return 0
    return trailing
