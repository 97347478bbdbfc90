"""Stage 4, matching: the image pairs to match.

Which pairs are matched (:func:`select_pairs`): every pair of featured images (``Pairs.EXHAUSTIVE``,
quadratic), or (``Pairs.AUTO``) the pairs a cheap first pass finds worth it: the
``FIRST_PASS_FEATURES`` largest-scale SIFT features of every image (the ones a low-resolution image would
give; already extracted, so the pass costs no extraction) are matched between every pair (mutual nearest
neighbours passing the ratio test, one matrix product per image), and each image keeps its
``neighbours`` best-scoring partners of other rigs, plus a maximum spanning tree of the rigs (the network
stays connected), plus the pairs inside a rig (its wide and narrow image of a frame, consecutive frames).
With narrow features, the narrow images of each rig's ``NARROW_NEIGHBOURS`` best wide partners are matched
too; other pairs with a narrow image need a first-pass score of ``MIN_NARROW_SCORE``: a wide and a narrow
image of two different rigs (4x the focal length) almost never verify and each costs a full matching. After mapping, ``rigsfm.run.checks.missed_pairs`` checks the skipped
pairs against the model (a warning if one would have shared many points)."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigsfm.core.graph import DisjointSets
from rigsfm.run.inputs.database import open_database
from rigsfm.run.inputs.images import ImageEntry
from rigsfm.run.matching.extract import featured_images
from rigsfm.run.options import MatchingOptions, Pairs

logger = logging.getLogger(__name__)


def image_pairs(images: Sequence[ImageEntry], options: MatchingOptions) -> list[tuple[str, str]]:
    """Every pair of featured images, except two images of the same frame without narrow features, and, with
    ``options.frame_offsets``, two narrow images of different rigs taken at different times."""
    featured = featured_images(images, options)
    times = narrow_times(images, options.frame_offsets)
    return [
        (a.name, b.name)
        for a, b in itertools.combinations(featured, 2)
        if not (a.rig == b.rig and a.frame == b.frame and not options.narrow_features)
        and not unsynchronised_pair(a, b, times)
    ]


def narrow_times(images: Sequence[ImageEntry], offsets: dict[str, int] | None) -> dict[str, int] | None:
    """Narrow image name -> its time in frames (its rig's k-th narrow frame at k + offset, rigsfm.run.checks.sync);
    None without offsets."""
    if offsets is None:
        return None
    frames: dict[str, list[ImageEntry]] = {}
    for entry in sorted(images, key=lambda e: e.frame):
        if entry.sensor == "narrow":
            frames.setdefault(entry.rig, []).append(entry)
    return {e.name: k + int(offsets.get(rig, 0)) for rig, entries in frames.items() for k, e in enumerate(entries)}


def unsynchronised_pair(a: ImageEntry, b: ImageEntry, times: dict[str, int] | None) -> bool:
    """Two narrow images of different rigs taken at different times: a moving crowd in them is not one scene."""
    return (times is not None and a.sensor == b.sensor == "narrow" and a.rig != b.rig
            and times.get(a.name) != times.get(b.name))


def drop_unsynchronised_pairs(database_path: Path, images: Sequence[ImageEntry],
                              offsets: dict[str, int] | None) -> int:
    """Delete the matches of narrow pairs of two rigs taken at different times (an earlier run's, made before the
    frame offsets were given); returns how many pairs were dropped."""
    times = narrow_times(images, offsets)
    if times is None:
        return 0
    narrow = [e for e in images if e.sensor == "narrow"]
    dropped = 0
    with open_database(database_path) as database:
        ids = {image.name: image.image_id for image in database.read_all_images()}
        for a, b in itertools.combinations(narrow, 2):
            if a.name in ids and b.name in ids and unsynchronised_pair(a, b, times) \
                    and database.exists_two_view_geometry(ids[a.name], ids[b.name]):
                database.delete_two_view_geometry(ids[a.name], ids[b.name])
                database.delete_matches(ids[a.name], ids[b.name])
                dropped += 1
    if dropped:
        logger.info("Dropped the matches of %d narrow pairs taken at different times (frame offsets)", dropped)
    return dropped


FIRST_PASS_FEATURES = 256  # largest-scale features per image matched in the first pass
MIN_NARROW_SCORE = 12  # first-pass matches a pair with a narrow image needs (random pairs score 2-8)
NARROW_NEIGHBOURS = 2  # with narrow features: narrow pairs of each rig's best wide partners, always matched


@dataclass
class PairSelection:
    """The pairs to match fully, out of every candidate pair, and why."""

    mode: Pairs
    pairs: list[tuple[str, str]]  # to match, in matching order
    num_candidates: int  # every pair exhaustive matching would match
    scores: dict[tuple[str, str], int] = field(default_factory=dict)  # first-pass matches per candidate (auto)
    first_pass_s: float = 0.0

    @property
    def skipped(self) -> list[tuple[str, str]]:
        chosen = set(self.pairs)
        return [pair for pair in self.scores if pair not in chosen]

    def summary(self) -> dict:
        return {"mode": str(self.mode), "candidates": self.num_candidates, "matched": len(self.pairs),
                "skipped": self.num_candidates - len(self.pairs), "first_pass_s": round(self.first_pass_s, 3)}


def first_pass_descriptors(database_path: Path, names: Sequence[str],
                           num_features: int = FIRST_PASS_FEATURES) -> dict[str, np.ndarray]:
    """Per image, its ``num_features`` largest-scale SIFT descriptors, unit length (float32)."""
    result = {}
    with open_database(database_path) as database:
        for name in names:
            # the images were just written
            image_id = database.read_image_with_name(name).image_id  # type: ignore[union-attr]
            keypoints = database.read_keypoints(image_id)
            descriptors = database.read_descriptors(image_id).data
            if len(keypoints) == 0:
                result[name] = np.zeros((0, 128), np.float32)
                continue
            scale = np.abs(keypoints[:, 2] * keypoints[:, 5] - keypoints[:, 3] * keypoints[:, 4])
            chosen = np.argsort(-scale, kind="stable")[:num_features]
            x = descriptors[chosen].astype(np.float32)
            result[name] = x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    return result


def first_pass_scores(descriptors: dict[str, np.ndarray], pairs: Sequence[tuple[str, str]],
                      max_ratio: float = 0.8) -> dict[tuple[str, str], int]:
    """Mutual nearest neighbours passing the ratio test between the first-pass descriptors of each pair.

    One matrix product per image against all its partners (padded to the same number of features)."""
    partners: dict[str, list[str]] = {}
    for a, b in pairs:
        partners.setdefault(a, []).append(b)
    size = max((len(d) for d in descriptors.values()), default=0)
    if size < 2:
        return {pair: 0 for pair in pairs}

    def padded(name: str) -> np.ndarray:
        d = descriptors[name]
        return np.vstack([d, np.zeros((size - len(d), d.shape[1]), np.float32)]) if len(d) < size else d

    scores = {}
    for a, others in partners.items():
        da = descriptors[a]
        if len(da) < 2:
            scores.update({(a, b): 0 for b in others})
            continue
        block = np.stack([padded(b) for b in others])  # (P, size, 128)
        similarity = np.einsum("id,pjd->pij", da, block)  # (P, n_a, size)
        valid = np.array([len(descriptors[b]) for b in others])
        padding = np.arange(size)[None, None, :] >= valid[:, None, None]
        similarity = np.where(padding, np.float32(-2.0), similarity)  # padding never matches
        top2 = -np.partition(-similarity, 1, axis=2)[:, :, :2]  # best, second best similarity
        distance = np.sqrt(np.maximum(0.0, 2.0 - 2.0 * top2))
        ratio_ok = distance[:, :, 0] < max_ratio * distance[:, :, 1]
        best_in_b = similarity.argmax(axis=2)  # (P, n_a)
        best_in_a = similarity.argmax(axis=1)  # (P, size)
        mutual = np.take_along_axis(best_in_a, best_in_b, axis=1) == np.arange(len(da))[None, :]
        counts = (ratio_ok & mutual).sum(axis=1)
        scores.update({(a, b): int(c) for b, c in zip(others, counts)})
    return {pair: scores[pair] for pair in pairs}


def _spanning_tree(nodes: Sequence[str], edges: dict[tuple[str, str], float]) -> list[tuple[str, str]]:
    """Maximum spanning forest (Kruskal) of ``nodes`` under ``edges`` (pair -> weight)."""
    sets = DisjointSets(nodes)
    return [(a, b) for (a, b), _ in sorted(edges.items(), key=lambda item: (-item[1], item[0])) if sets.union(a, b)]


def select_pairs(database_path: Path, images: Sequence[ImageEntry], options: MatchingOptions) -> PairSelection:
    """The pairs to match (see the module docstring): every candidate, or the first pass's choice."""
    import time

    candidates = image_pairs(images, options)
    if options.pairs == Pairs.EXHAUSTIVE:
        return PairSelection(Pairs.EXHAUSTIVE, candidates, len(candidates))
    start = time.perf_counter()
    entry = {e.name: e for e in images}
    featured = [e.name for e in featured_images(images, options)]
    frames = {rig: sorted({e.frame for e in images if e.rig == rig}) for rig in {e.rig for e in images}}

    def inside_rig(a: str, b: str) -> bool:  # a frame's wide and narrow image, or consecutive frames
        ea, eb = entry[a], entry[b]
        if ea.frame == eb.frame:
            return True
        order = frames[ea.rig]
        return ea.sensor == eb.sensor and abs(order.index(ea.frame) - order.index(eb.frame)) == 1

    keep = {pair for pair in candidates if entry[pair[0]].rig == entry[pair[1]].rig and inside_rig(*pair)}
    between = [pair for pair in candidates if entry[pair[0]].rig != entry[pair[1]].rig]
    scores = first_pass_scores(first_pass_descriptors(database_path, featured), between, options.max_ratio)
    ranked: dict[str, list[tuple[int, str, tuple[str, str]]]] = {}
    for pair, score in scores.items():
        wide_only = entry[pair[0]].sensor == entry[pair[1]].sensor == "wide"
        if not wide_only and score < MIN_NARROW_SCORE:
            continue
        for one, other in (pair, pair[::-1]):
            ranked.setdefault(one, []).append((-score, other, pair))
    for partners in ranked.values():
        keep.update(pair for _, _, pair in sorted(partners)[: options.neighbours])
    # The narrow images of neighbouring rigs see the same crowd from close directions: match them for the
    # NARROW_NEIGHBOURS best wide partners of each wide image (those of adjacent rigs are the narrow pairs that
    # verify, and they make the narrow poses more accurate; see benchmarks/README.md).
    narrow_of = {(e.rig, e.frame): e.name for e in images if e.sensor == "narrow" and e.name in set(featured)}
    order_of = {pair: i for i, pair in enumerate(candidates)}
    for name, partners in ranked.items():
        if entry[name].sensor != "wide":
            continue
        wide_partners = [other for _, other, _ in sorted(partners) if entry[other].sensor == "wide"]
        for other in wide_partners[:NARROW_NEIGHBOURS]:
            a = narrow_of.get((entry[name].rig, entry[name].frame))
            b = narrow_of.get((entry[other].rig, entry[other].frame))
            if a and b and ((a, b) in order_of or (b, a) in order_of):  # not when taken at different times
                keep.add((a, b) if (a, b) in order_of else (b, a))
    rig_links: dict[tuple[str, str], tuple[int, tuple[str, str]]] = {}
    for pair, score in scores.items():
        if entry[pair[0]].sensor == entry[pair[1]].sensor == "wide":
            link = tuple(sorted((entry[pair[0]].rig, entry[pair[1]].rig)))
            if score > rig_links.get(link, (-1, None))[0]:  # type: ignore[arg-type]  # two rigs; (-1, None): none yet
                rig_links[link] = (score, pair)  # type: ignore[index]  # sorted: two rigs
    tree = _spanning_tree(sorted(frames), {link: score for link, (score, _) in rig_links.items()})
    keep.update(rig_links[link][1] for link in tree)
    pairs = sorted(keep, key=order_of.__getitem__)
    all_scores = {pair: scores.get(pair, -1) for pair in candidates}  # -1: inside a rig, not scored
    selection = PairSelection(Pairs.AUTO, pairs, len(candidates), all_scores, time.perf_counter() - start)
    logger.info("Pairs: %d of %d chosen by a first pass over %d images (%.1f s)", len(pairs), len(candidates),
                len(featured), selection.first_pass_s)
    return selection
