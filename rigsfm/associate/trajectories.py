"""Each person's track through a recording: which person of the frame before a person of this frame is.

A frame's persons are found on that frame's evidence, but a crowd's analyst wants who walked where. Two consecutive
frames' persons are linked one to one (an assignment over the whole frame, not nearest first) by the likelihood of
each floor displacement against a person appearing there by chance (the frame before's local density of persons):
a person walks from where it stood, about a walk between the frames plus both points' floor covariances, or, where
its track brings its step from the frame before, repeats that step about a smaller walk of its own (walkers keep
their heading; a mixture of both, since a step may be a wrong link's). The walks and the mixture's weights are the
recording's own, estimated per frame pair by expectation-maximisation over every person within reach (a dense
crowd's nearest person is not always the same one). Each link says how likely it is right (its probability over
every way the two frames' persons could pair, each continuing at most one: belief propagation over the pairs), and a
track goes on only through a link likelier right than wrong: where the walk between frames reaches the crowd's
spacing (2 frames a second in a dense crowd) the links stay, with their low confidences, but the tracks break. A
person found in one frame and missed in the next (seen in fewer than two views) ends its track too; its next finding
starts another.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

REACH_M = 2.0  # the farthest a person walks between two frames of a recording (4 m/s at 2 frames a second)
START_WALK_M = 0.3  # the walk per floor axis the estimate starts from
MIN_WALK_M = 0.01  # a floor for the estimate: standing crowds still move their heads' points by their noise
EM_ROUNDS = 30
NEGLIGIBLE_LOG_RATIO = -12.0  # a pair this much less likely than chance changes no link's probability
TRACK_CONFIDENCE = 0.5  # a track goes on through a link likelier right than wrong


@dataclass(frozen=True, kw_only=True)
class Links:
    """One frame's persons linked to the frame before's."""

    earlier: np.ndarray  # per person of this frame, the frame before's person it continues, or -1
    walk_m: float | None  # the walk per floor axis from where a person stood (m); None: too few persons to say
    # per person, the probability that its link is right (against every other way this frame's and the frame before's
    # persons within reach could pair, or appear and leave by chance); NaN: not linked
    confidence: np.ndarray


def _floor_pairs(earlier: np.ndarray, later: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every (earlier, later) pair of persons within ``REACH_M`` on the floor."""
    if not len(earlier) or not len(later):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    near = cKDTree(earlier[:, :2]).sparse_distance_matrix(cKDTree(later[:, :2]), REACH_M, output_type="ndarray")
    return near["i"].astype(np.int64), near["j"].astype(np.int64)


def link_persons(earlier_points: np.ndarray, earlier_covariances: np.ndarray, points: np.ndarray,
                 covariances: np.ndarray, velocity: np.ndarray | None = None,
                 velocity_covariances: np.ndarray | None = None, walk_m: float | None = None) -> Links:
    """Link the persons at ``points`` (P x 3, covariances P x 3 x 3) to the frame before's. ``velocity``: per earlier
    person, its step from the frame before it (E x 2 on the floor; NaN: none known), which it may repeat
    (``velocity_covariances``: what that prediction adds to its floor covariance, E x 2 x 2): such a person's next
    point is a mixture of its repeated step (about a walk of its own) and a walk from where it stood (its step may
    have been a wrong link's), their weights and walks estimated with the rest. ``walk_m``: the walk from where a
    person stood, given (a recording's first link's) instead of estimated: once the walkers repeat their steps, those
    left to it are mostly the association's chance persons, whose spread would widen it."""
    moving = np.zeros(len(earlier_points), bool) if velocity is None else np.isfinite(velocity[:, 0])
    predicted = earlier_points[:, :2].copy()
    if velocity is not None:
        predicted[moving] += velocity[moving]
    i, j = _floor_pairs(earlier_points[:, :2], points)
    if moving.any():  # and the pairs within reach of a repeated step
        near_i, near_j = _floor_pairs(predicted[moving], points)
        pairs = np.unique(np.r_[np.c_[i, j], np.c_[np.flatnonzero(moving)[near_i], near_j]], axis=0)
        i, j = pairs[:, 0], pairs[:, 1]
    earlier = np.full(len(points), -1)
    confidence = np.full(len(points), np.nan)
    if len(i) < 3:
        return Links(earlier=earlier, walk_m=None, confidence=confidence)
    d = points[j, :2] - earlier_points[i, :2]
    both = covariances[j, :2, :2] + earlier_covariances[i, :2, :2]
    spread = np.einsum("ni,ni->n", d, d) - np.trace(both, axis1=1, axis2=2)
    repeats = moving[i]  # the pairs whose earlier person may repeat its step
    d_step = points[j[repeats], :2] - predicted[i[repeats]]
    both_step = both[repeats] + (velocity_covariances[i[repeats]] if velocity_covariances is not None else 0.0)
    spread_step = np.einsum("ni,ni->n", d_step, d_step) - np.trace(both_step, axis1=1, axis2=2)
    # chance: the frame before's persons per m^2 round each of this frame's persons
    density = np.bincount(j, minlength=len(points)) / (math.pi * REACH_M ** 2)
    walk = START_WALK_M if walk_m is None else walk_m
    walk_step = walk
    share = 0.5  # of this frame's persons that continue one of the frame before's
    repeat = 0.5  # of the persons with a step that repeat it

    def log_likelihood() -> tuple[np.ndarray, np.ndarray]:
        """Each pair's log-likelihood, and per repeating pair the repeated step's share of it."""
        log_l = _log_normal(d, both, walk)
        if not repeats.any():
            return log_l, np.zeros(0)
        stood = math.log(1 - repeat) + log_l[repeats]
        stepped = math.log(repeat) + _log_normal(d_step, both_step, walk_step)
        log_l[repeats] = np.logaddexp(stood, stepped)
        return log_l, np.exp(stepped - log_l[repeats])

    for _ in range(EM_ROUNDS):
        log_l, stepped = log_likelihood()
        # per later person: its candidates' posterior against chance
        weight = np.exp(log_l - np.log(density[j]))
        total = np.bincount(j, weights=weight, minlength=len(points)) + (1 - share) / share
        r = weight / total[j]
        if r.sum() < 3:
            return Links(earlier=earlier, walk_m=None, confidence=confidence)
        # each walk: its responsibilities' displacements less the points' own floor variance, per axis (the
        # repeated steps' with too few persons to say takes the other's)
        stood_r = r.copy()
        stood_r[repeats] *= 1 - stepped
        step_r = r[repeats] * stepped
        new = math.sqrt(max(float(np.sum(stood_r * spread) / (2 * stood_r.sum())), MIN_WALK_M ** 2)) \
            if walk_m is None else walk_m
        new_step = math.sqrt(max(float(np.sum(step_r * spread_step) / (2 * step_r.sum())), MIN_WALK_M ** 2)) \
            if step_r.sum() >= 3 else new
        new_repeat = min(max(float(step_r.sum() / max(r[repeats].sum(), 1e-12)), 0.01), 0.99) \
            if step_r.sum() >= 3 else repeat
        new_share = min(max(float(r.sum() / len(points)), 0.01), 0.99)
        converged = abs(new - walk) < 1e-4 * walk and abs(new_step - walk_step) < 1e-4 * walk_step \
            and abs(new_share - share) < 1e-4 and abs(new_repeat - repeat) < 1e-4
        walk, walk_step, share, repeat = new, new_step, new_share, new_repeat
        if converged:
            break
    log_lr = log_likelihood()[0] - np.log(density[j]) + math.log(share / (1 - share))
    # the pairs that can weigh in a person's posterior at all (the others' ratios are 0 to the posteriors' digits)
    weighs = log_lr > NEGLIGIBLE_LOG_RATIO
    posterior = np.zeros(len(log_lr))
    posterior[weighs] = _exclusive_posterior(i[weighs], j[weighs], np.exp(np.minimum(log_lr[weighs], 700.0)),
                                             len(earlier_points), len(points))
    keep = log_lr > 0  # a link likelier than a person appearing there
    if keep.any():
        ei, ej, gain = i[keep], j[keep], log_lr[keep]
        rows, row_of = np.unique(ej, return_inverse=True)
        cols, col_of = np.unique(ei, return_inverse=True)
        cost = np.zeros((len(rows), len(cols)))  # 0: left unlinked
        cost[row_of, col_of] = -gain
        probability = np.zeros((len(rows), len(cols)))
        probability[row_of, col_of] = posterior[keep]
        a, b = linear_sum_assignment(cost)
        linked = cost[a, b] < 0
        earlier[rows[a[linked]]] = cols[b[linked]]
        confidence[rows[a[linked]]] = probability[a[linked], b[linked]]
    return Links(earlier=earlier, walk_m=walk, confidence=confidence)


def _exclusive_posterior(i: np.ndarray, j: np.ndarray, ratio: np.ndarray, earlier: int, later: int,
                         rounds: int = 200) -> np.ndarray:
    """Each pair's probability of being a link when every person continues at most one and is continued by at most
    one (each later person otherwise new, each earlier one otherwise gone): belief propagation over the pairs'
    likelihood ratios (Williams & Lau's marginal association probabilities; exact for a person with one candidate, a
    candidate that another person claims counts less)."""
    nu = np.ones(len(ratio))
    for _ in range(rounds):
        held = ratio * nu
        mu = ratio / (1.0 + np.bincount(i, weights=held, minlength=earlier)[i] - held)
        new = 1.0 / (1.0 + np.bincount(j, weights=mu, minlength=later)[j] - mu)
        if np.max(np.abs(new - nu)) < 1e-6:
            nu = new
            break
        nu = new
    held = ratio * nu
    return held / (1.0 + np.bincount(i, weights=held, minlength=earlier)[i])


def _log_normal(d: np.ndarray, covariance: np.ndarray, walk: float | np.ndarray) -> np.ndarray:
    """log N(d; 0, covariance + walk^2 I) of 2-vectors, row by row (``walk``: one, or one per row), in closed form."""
    a = covariance[:, 0, 0] + walk ** 2
    b = covariance[:, 0, 1]
    c = covariance[:, 1, 1] + walk ** 2
    det = np.maximum(a * c - b * b, 1e-12)
    quad = (c * d[:, 0] ** 2 - 2 * b * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / det
    return -math.log(2 * math.pi) - 0.5 * np.log(det) - 0.5 * quad


def _steps(first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray], links: Links | None,
           ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per person of ``second``, its step on the floor from ``first`` where its track went on (NaN elsewhere), and what
    repeating that step adds to the floor covariance of its prediction (the second point counted twice over, the
    first once more: 3 C2 + C1 on top of C2)."""
    if links is None:
        return None, None
    (points1, covariances1), (points2, covariances2) = first, second
    going_on = (links.earlier >= 0) & (np.nan_to_num(links.confidence) > TRACK_CONFIDENCE)
    velocity = np.full((len(points2), 2), np.nan)
    added = np.zeros((len(points2), 2, 2))
    came = links.earlier[going_on]
    velocity[going_on] = points2[going_on, :2] - points1[came, :2]
    added[going_on] = 3 * covariances2[going_on, :2, :2] + covariances1[came, :2, :2]
    return velocity, added


def tracks(frames: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list[np.ndarray], list[Links | None]]:
    """Per frame (its persons' points and covariances, in recording order), each person's track number (the first
    frame's persons 0..P-1, then each new track the next number; a person continues its link's track where the link
    is confident) and its links to the frame before (None: the first frame)."""
    ids: list[np.ndarray] = []
    links: list[Links | None] = []
    following = 0
    for k, (points, covariances) in enumerate(frames):
        track = np.full(len(points), -1)
        found = None
        if k:
            before_points, before_covariances = frames[k - 1]
            velocity, velocity_covariances = _steps(frames[k - 2], frames[k - 1], links[-1]) if k > 1 else (None, None)
            # the walk from where a person stood: the first link's, before any step repeats
            first_walk = next((link.walk_m for link in links if link is not None), None) if k > 1 else None
            found = link_persons(before_points, before_covariances, points, covariances, velocity,
                                 velocity_covariances, first_walk)
            goes_on = (found.earlier >= 0) & (np.nan_to_num(found.confidence) > TRACK_CONFIDENCE)
            track[goes_on] = ids[-1][found.earlier[goes_on]]
        new = track < 0
        track[new] = following + np.arange(int(new.sum()))
        following += int(new.sum())
        ids.append(track)
        links.append(found)
    return ids, links
