"""Rendered crowds' truth for association: synthetic detections and the scores of an association against it.

Used by the tests and ``benchmarks/associate.py``; a dataset rendered with persons (rigsfm.synth.persons) holds
``persons/heads.csv`` (each head's exact pixel and visibility per image) and ``persons/frameNNNN.json`` (the head
centres in the truth's world frame).
"""

from __future__ import annotations

import csv
import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigsfm.core.geometry import align_points
from rigsfm.core.names import ImageName


@dataclass
class SyntheticDetections:
    """Per narrow image: detections (raw COLMAP pixels) and the true person of each (-1: a false detection)."""

    points: dict[str, np.ndarray]
    person: dict[str, np.ndarray]
    radius: dict[str, np.ndarray] | None = None  # apparent head radii (px), where simulated

    def csv_text(self) -> str:
        lines = ["image,x,y"]
        for name, xy in self.points.items():
            lines += [f"{name},{x:.3f},{y:.3f}" for x, y in xy]
        return "\n".join(lines) + "\n"


def visible_heads(dataset: Path, frame: str = "frame0000") -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per narrow image of ``frame``: the visible heads' pixels and person ids."""
    out: dict[str, list] = {}
    with open(Path(dataset) / "persons" / "heads.csv", newline="") as f:
        for row in csv.DictReader(f):
            name = ImageName.parse(row["image"])
            if not name.is_narrow or not name.frame.startswith(frame) or row["visible"] != "1":
                continue
            out.setdefault(row["image"], []).append((float(row["x"]), float(row["y"]), int(row["person"])))
    return {k: (np.array([r[:2] for r in v]), np.array([r[2] for r in v])) for k, v in sorted(out.items())}


def true_head_radii(dataset: Path, heads: dict[str, tuple[np.ndarray, np.ndarray]], frame: int = 0, *,
                    spread: float = 0.1, seed: int = 0) -> dict[str, np.ndarray]:
    """Per image of ``heads``, each visible head's apparent radius (px): f R / distance from the truth's camera
    centre to the head centre, R the rendered head radius times a person's own factor (lognormal, ``spread``)."""
    import json

    import pycolmap

    data = json.loads((Path(dataset) / "persons" / f"frame{frame:04d}.json").read_text())
    centres3d = np.asarray(data["instants"][0]["heads"], dtype=np.float64)
    factor = np.exp(spread * np.random.default_rng([seed, 71]).normal(size=len(centres3d)))
    radius_m = float(data["head_radius_m"]) * factor
    truth = pycolmap.Reconstruction(str(Path(dataset) / "ground_truth"))
    images = {image.name: image for image in truth.images.values()}
    out = {}
    for name, (_, ids) in heads.items():
        image = images[name]
        centre = np.asarray(image.projection_center())
        focal = float(np.sqrt(abs(image.camera.focal_length_x * image.camera.focal_length_y)))
        dist = np.linalg.norm(centres3d[ids] - centre[None], axis=1)
        out[name] = focal * radius_m[ids] / dist
    return out


def make_detections(heads: dict[str, tuple[np.ndarray, np.ndarray]], sizes: dict[str, tuple[int, int]], *,
                    sigma_px: float = 1.5, missed: float = 0.1, false: float = 0.05, seed: int = 0,
                    radii: dict[str, np.ndarray] | None = None, size_noise: float = 0.1,
                    ) -> SyntheticDetections:
    """True visible heads plus normal noise, each missed with probability ``missed``, plus ``false`` x as many
    false detections uniform in the image; images without a model (not in ``sizes``) are left out. ``radii``: the
    visible heads' true apparent radii (px): each detection's is multiplied by lognormal noise (``size_noise``), a
    false one's is a random visible head's of its image, with 20 % lognormal noise (the points are the same as
    without radii)."""
    rng = np.random.default_rng(seed)
    size_rng = np.random.default_rng([seed, 72])
    points, person, radius = {}, {}, {}
    for name, (xy, ids) in heads.items():
        if name not in sizes:
            continue
        width, height = sizes[name]
        keep = rng.random(len(xy)) >= missed
        noisy = xy[keep] + rng.normal(0.0, sigma_px, (int(keep.sum()), 2))
        n_false = rng.binomial(len(xy), false) if len(xy) else 0
        fake = rng.uniform([0, 0], [width, height], (n_false, 2))
        all_xy = np.clip(np.concatenate([noisy, fake]), [0, 0], [width, height])
        points[name] = all_xy
        person[name] = np.concatenate([ids[keep], -np.ones(n_false, dtype=np.int64)])
        if radii is not None:
            true_r = radii[name][keep] * np.exp(size_noise * size_rng.normal(size=int(keep.sum())))
            pool = radii[name] if len(radii[name]) else np.array([10.0])
            fake_r = size_rng.choice(pool, n_false) * np.exp(0.2 * size_rng.normal(size=n_false))
            radius[name] = np.concatenate([true_r, fake_r])
    return SyntheticDetections(points, person, radius if radii is not None else None)


@dataclass
class Scores:
    pair_precision: float
    pair_recall: float
    pair_f1: float
    person_precision: float
    person_recall: float
    person_f1: float
    persons: int
    true_persons: int


def _f1(p: float, r: float) -> float:
    return 2 * p * r / (p + r) if p + r > 0 else 0.0


def score_groups(groups: list[list[tuple[str, int]]], truth: SyntheticDetections) -> Scores:
    """Pairwise precision/recall (pairs of detections in different views put together) and person-level F1 (a
    person is right when all its detections are one true person's and it holds at least two).

    ``groups``: per found person, its detections as (image, index in ``truth.points[image]``)."""
    def pid(image, index):
        return int(truth.person[image][index])

    found_pairs = set()
    for group in groups:
        for a, b in itertools.combinations(sorted(group), 2):
            found_pairs.add((a, b))
    true_sets: dict[int, list] = {}
    for image, ids in truth.person.items():
        for index, p in enumerate(ids):
            if p >= 0:
                true_sets.setdefault(int(p), []).append((image, index))
    true_pairs: set[tuple] = set()
    for members in true_sets.values():
        true_pairs.update(itertools.combinations(sorted(members), 2))
    hit = sum(1 for a, b in found_pairs if pid(*a) >= 0 and pid(*a) == pid(*b))
    precision = hit / len(found_pairs) if found_pairs else 1.0
    recall = hit / len(true_pairs) if true_pairs else 1.0
    true_multi = {p for p, m in true_sets.items() if len(m) >= 2}
    correct = 0
    for group in groups:
        persons = {pid(*m) for m in group}
        if len(persons) == 1 and next(iter(persons)) >= 0:
            correct += 1
    pp = correct / len(groups) if groups else 1.0
    pr = correct / len(true_multi) if true_multi else 1.0
    return Scores(precision, recall, _f1(precision, recall), pp, pr, _f1(pp, pr), len(groups), len(true_multi))


CONFIDENCE_BINS = (0.0, 0.2, 0.4, 0.6, 0.8, 0.95, 0.99, 1.0)


def reliability(groups: list[list[tuple[str, int]]], confidence: np.ndarray, truth: SyntheticDetections,
                bins: tuple[float, ...] = CONFIDENCE_BINS) -> list[dict]:
    """The persons' confidence against how often they are right (all detections one true person's, as in
    :func:`score_groups`), per confidence bin (the last includes 1): persons, mean confidence, share right."""
    right = np.array([len(ids := {int(truth.person[image][index]) for image, index in group}) == 1
                      and next(iter(ids)) >= 0 for group in groups], dtype=bool)
    confidence = np.asarray(confidence, dtype=float)
    out = []
    for k, (lo, hi) in enumerate(zip(bins[:-1], bins[1:])):
        inside = (confidence >= lo) & ((confidence < hi) | (k == len(bins) - 2))
        if inside.any():
            out.append({"bin": [lo, hi], "persons": int(inside.sum()),
                        "mean_confidence": float(confidence[inside].mean()),
                        "right": float(right[inside].mean())})
    return out


def rigid_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising |R source + t - target| (no scale: a wrong metric scale stays an error)."""
    target_from_source = align_points(source, target, scaled=False)
    if target_from_source is None:
        raise ValueError("three or more points off one line are needed to align the run onto the truth")
    return target_from_source.rotation.matrix(), np.asarray(target_from_source.translation)


def truth_from_run(run, truth) -> tuple[np.ndarray, np.ndarray]:
    """R, t taking the run's world to the truth's, from the centres of the images both hold (pycolmap models)."""
    by_name = {image.name: image for image in truth.images.values()}
    pairs = [(np.asarray(image.projection_center()), np.asarray(by_name[image.name].projection_center()))
             for image in run.images.values() if image.has_pose and image.name in by_name]
    source, target = np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs])
    return rigid_alignment(source, target)


def true_heads(dataset: Path, frame: int = 0) -> np.ndarray:
    """Head centres (P x 3, the truth's world) of frame ``frame`` (synchronised rigs: its first instant)."""
    import json

    data = json.loads((Path(dataset) / "persons" / f"frame{frame:04d}.json").read_text())
    return np.asarray(data["instants"][0]["heads"], dtype=np.float64)
