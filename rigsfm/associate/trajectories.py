"""Each person's track through a recording: which person of the frame before a person of this frame is.

A frame's persons are found on that frame's evidence, but a crowd's analyst wants who walked where. Two consecutive
frames' persons are linked one to one (an assignment over the whole frame, not nearest first) by the likelihood of
each floor displacement: a person continues one of the frame before's, displaced by the walk between the frames
plus both points' floor covariances, against appearing there by chance (the frame before's local density of
persons). The walk is the recording's own, estimated per frame pair by expectation-maximisation over every person
within reach (a dense crowd's nearest person is not always the same one), so 2 and 10 frames a second both link.
Each link says how likely it is right (its probability over every way the two persons could have come there, each
person continuing at most one: belief propagation over the frame's pairs), and a track goes on only through a link
likelier right than wrong: where the walk between frames reaches the crowd's
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
    walk_m: float | None  # the walk per floor axis between the two frames (m); None: too few persons to say
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
                 covariances: np.ndarray) -> Links:
    """Link the persons at ``points`` (P x 3, covariances P x 3 x 3) to the frame before's."""
    i, j = _floor_pairs(earlier_points, points)
    earlier = np.full(len(points), -1)
    confidence = np.full(len(points), np.nan)
    if len(i) < 3:
        return Links(earlier=earlier, walk_m=None, confidence=confidence)
    d = points[j, :2] - earlier_points[i, :2]
    both = covariances[j, :2, :2] + earlier_covariances[i, :2, :2]
    # chance: the frame before's persons per m^2 round each of this frame's persons
    density = np.bincount(j, minlength=len(points)) / (math.pi * REACH_M ** 2)
    spread = np.einsum("ni,ni->n", d, d) - np.trace(both, axis1=1, axis2=2)
    walk = START_WALK_M
    share = 0.5  # of this frame's persons that continue one of the frame before's
    for _ in range(EM_ROUNDS):
        log_l = _log_normal(d, both, walk)
        # per later person: its candidates' posterior against chance
        weight = np.exp(log_l - np.log(density[j]))
        total = np.bincount(j, weights=weight, minlength=len(points)) + (1 - share) / share
        r = weight / total[j]
        if r.sum() < 3:
            return Links(earlier=earlier, walk_m=None, confidence=confidence)
        # the walk: the responsibilities' displacements less the points' own floor variance, per axis
        new = math.sqrt(max(float(np.sum(r * spread) / (2 * r.sum())), MIN_WALK_M ** 2))
        new_share = min(max(float(r.sum() / len(points)), 0.01), 0.99)
        converged = abs(new - walk) < 1e-4 * walk and abs(new_share - share) < 1e-4
        walk, share = new, new_share
        if converged:
            break
    log_lr = _log_normal(d, both, walk) - np.log(density[j]) + math.log(share / (1 - share))
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


def _log_normal(d: np.ndarray, covariance: np.ndarray, walk: float) -> np.ndarray:
    """log N(d; 0, covariance + walk^2 I) of 2-vectors, row by row, in closed form."""
    a = covariance[:, 0, 0] + walk ** 2
    b = covariance[:, 0, 1]
    c = covariance[:, 1, 1] + walk ** 2
    det = np.maximum(a * c - b * b, 1e-12)
    quad = (c * d[:, 0] ** 2 - 2 * b * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / det
    return -math.log(2 * math.pi) - 0.5 * np.log(det) - 0.5 * quad


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
            found = link_persons(before_points, before_covariances, points, covariances)
            goes_on = (found.earlier >= 0) & (np.nan_to_num(found.confidence) > TRACK_CONFIDENCE)
            track[goes_on] = ids[-1][found.earlier[goes_on]]
        new = track < 0
        track[new] = following + np.arange(int(new.sum()))
        following += int(new.sum())
        ids.append(track)
        links.append(found)
    return ids, links
