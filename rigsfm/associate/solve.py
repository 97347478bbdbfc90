"""Multi-view association of point detections (heads) in synchronised narrow images into 3D persons.

Per frame:

1. Each detection becomes a ray (undistorted through its camera, in the run's world frame). Each view gets a pose
   sigma in pixels from the run's calibrated 95 % bands (``band_ij / 1.96`` squared = ``s_i^2 + s_j^2``, solved for
   the ``s`` by non-negative least squares); a detection's reprojection noise is ``s_view^2 + pixel_sigma^2``.
2. Candidates for each pair (i, j): detections of j within ``gate_sigmas`` of the segment that i's ray between the
   two heights projects to in j (the band of the epipolar line, cut to the height range), triangulated.
3. Every candidate grows into a multi-view hypothesis: in every other view the detection nearest (Mahalanobis:
   the point's projected covariance plus that view's noise) to the point's projection joins when inside the gate;
   the point is re-triangulated (weighted: each ray by its distance and noise), members whose reprojection falls
   outside their band are dropped, twice over. Hypotheses outside the height range are dropped.
4. Each hypothesis scores its log-likelihood ratio against "these detections are clutter": per member
   ``log(p_d / clutter density) - log(2 pi s^2) - d^2 / 2``, per view that sees the point inside its image and has
   no member ``log(1 - p_d)`` (``p_d`` each view's own from the crowd's occlusion, rates.Occlusion, once the
   crowd's rates are estimated), and once the prior density of persons in the crowd's volume times the volume the
   point's covariance leaves (``log rho + 3/2 log 2 pi + 1/2 log det Sigma``: two views fix a point much less
   than four). A global set packing (each detection in at most one person; scipy's MILP) keeps the
   set of hypotheses with the largest summed score.
5. Self-calibration: a view's pose error moves all its detections alike, by more than the heads' spacing allows a
   band to absorb. Per view a shift of its undistorted pixels (a small rotation) is estimated, first from the pairs
   (pairwise_view_shifts), then from the confident groups (estimate_view_shifts), each under the run's pose sigma as
   its prior (the pairs' from their distances alone and with where the candidates' rays meet, the crowd's heights:
   whichever associates into more confident groups); the frame is associated again with the shifted views and the
   bands the shift leaves. A correction is kept only where it leaves more confident groups than before.

The views are in views.py, a frame's stacked detections and their arithmetic (steps 1-4) in frame.py, the packing in
packing.py, the self-calibration (step 5) in shifts.py; this module associates a frame with them.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import numpy as np

from rigsfm.associate.appearance import AppearanceModel, describe, estimate, head_radius_px
from rigsfm.associate.frame import _Frame
from rigsfm.associate.options import AssociateOptions
from rigsfm.associate.packing import _pack
from rigsfm.associate.rates import Occlusion, detection_noise, fit_occlusion, truncated_binomial_p
from rigsfm.associate.shifts import (
    ViewCorrection,
    _apply_correction,
    _confident,
    _corrected,
    _epipolar_offsets,
    _warn_beyond_band,
    estimate_view_shifts,
    pairwise_view_shifts,
)
from rigsfm.associate.tracked import seen_before
from rigsfm.associate.views import View

logger = logging.getLogger(__name__)


@dataclass
class FrameResult:
    """The persons of one frame: per person its point, covariance, score, confidence and member detections."""

    views: list[str]
    points: np.ndarray  # P x 3 world metres
    covariances: np.ndarray  # P x 3 x 3
    scores: np.ndarray  # P: log-likelihood ratio against clutter
    members: np.ndarray  # P x V: index of the detection in each view's list, or -1
    detection_probability: float | None = None  # the crowd's, as this frame's persons say it
    height_prior: tuple[float, float] | None = None  # mean and sigma (m) of the persons' heights, as they say it
    appearance: AppearanceModel | None = None  # the appearance cue's model, where the images gave one
    head_radius_m: float | None = None  # the crowd's mean head radius, where the detections gave radii
    # Per view, the shift (undistorted px) and band sigma the persons were found with; a carried frame's views go on
    # to hold the shifts refined from its persons, for the next frame.
    shift_px: dict[str, np.ndarray] = field(default_factory=dict)
    band_sigma_px: dict[str, float] = field(default_factory=dict)
    occlusion: Occlusion | None = None  # each view's detection probability from the crowd's occlusion, where fitted (not carried)
    pixel_sigma: float | None = None  # the detector's noise (px) the persons were found with

    @property
    def confidence(self) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.clip(self.scores, -50, 50)))

    def __len__(self) -> int:
        return len(self.points)


def _solve(views: list[View], options: AssociateOptions, appearance: AppearanceModel | None = None,
           frame: _Frame | None = None, earlier: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
           ) -> tuple[_Frame, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """One association of a frame: hypotheses, their scores (with the appearance term where given) and the global
    packing. ``frame``: an earlier association's frame of the same ``views`` (their shifts and bands unchanged),
    whose grown groups are re-scored instead of grown again. ``earlier``: an earlier frame's persons (points,
    covariances), looked for first (``_Frame._tracked_hypotheses``)."""
    reused = frame.rescored(views, options, appearance) if frame is not None else None
    frame = _Frame(views, options, appearance, earlier) if reused is None else reused
    total = int(frame.offsets[-1])
    members, points, covariance, scores = frame.hypotheses()
    positive = scores > options.min_score
    members, points, covariance, scores = members[positive], points[positive], covariance[positive], scores[positive]
    chosen = _pack(members, scores - options.min_score, total, options.time_limit_s)
    if options.second_pass:
        # What the packing left: its hypotheses re-scored against the detections still free (a person seen in two
        # views competes with far fewer chance matches once the crowd's well-seen persons hold theirs), packed again.
        free = np.ones(total, dtype=bool)
        kept = members[chosen]
        free[kept[kept >= 0]] = False
        everyone = frame.clutter  # every detection's (the frame's own): put back after
        frame.clutter = frame.clutter_among(free)
        rest_m, rest_p, rest_c, rest_s = frame.hypotheses(free)
        more = rest_s > options.min_score
        if more.any():
            rest_m, rest_p, rest_c, rest_s = rest_m[more], rest_p[more], rest_c[more], rest_s[more]
            extra = _pack(rest_m, rest_s - options.min_score, total, options.time_limit_s)
            members = np.concatenate([members[chosen], rest_m[extra]])
            points = np.concatenate([points[chosen], rest_p[extra]])
            covariance = np.concatenate([covariance[chosen], rest_c[extra]])
            scores = np.concatenate([scores[chosen], rest_s[extra]])
            frame.clutter = everyone
            return frame, members, points, covariance, scores, int(positive.sum())
        frame.clutter = everyone
    return frame, members[chosen], points[chosen], covariance[chosen], scores[chosen], int(positive.sum())


def _centre_term(views: list[View], members: np.ndarray) -> np.ndarray:
    """Per group (G x 3 x 3), the covariance its views' own position errors add to its point.

    The cameras' position errors are shared by every person they see, so they do not shrink with more views: each
    person carries its views' mean centre covariance on top of the triangulation's; the views' errors move together
    (the network bends as a whole), so their mean is not divided by the number of views. The run's 3x3 says how the
    error leans (a ring of rigs moves more horizontally than vertically); where the run gives only the root of its
    trace, each axis holds a third of its square."""
    centre = np.array([v.centre_covariance_m2 if v.centre_covariance_m2 is not None
                       else v.centre_sigma_m ** 2 / 3.0 * np.eye(3) for v in views]).reshape(len(views), 3, 3)
    present = (members >= 0).astype(np.float64)
    return np.einsum("gv,vij->gij", present, centre) / np.maximum(present.sum(axis=1), 1)[:, None, None]


def associate_views(views: list[View], options: AssociateOptions, carried: bool = False,
                    earlier: FrameResult | None = None) -> FrameResult:
    """Persons seen by the detections of one frame's views (each view: pose, camera and raw detections).

    Every view's pose error is shared by all the persons it sees. With ``options.self_calibration_rounds`` > 0 the
    views are first shifted by the pairs' own evidence (pairwise_view_shifts: the distances alone and with the
    candidates' heights, the one whose association holds more confident groups), then, each round, by the confident
    groups of the last association (estimate_view_shifts), and the frame associated again with the shifted views
    and their tightened bands. A correction is kept only where it leaves more confident groups than before, and the
    pairs' one only where those are enough to re-estimate the shifts from (the crowd's own test of it: wrong shifts
    under tight bands break the groups up); the views are updated in place.

    ``carried``: the views already hold the shifts and head sizes of earlier frames of the same cameras (a static
    rig's pose error is the same in every frame): one association, with ``earlier``'s appearance model where it has
    one, whose confident groups refine the shifts in place for the next frame.
    ``earlier``: an earlier frame's result, whose detection probability, heights and (``carried``) appearance model
    this one takes (where ``options`` leaves them to the crowd).

    The appearance model is estimated once, from the first frame's association without it, and carried as the rates
    are: groups found under a model look alike by construction, so a model re-estimated from them would narrow frame
    by frame. A carried frame without an earlier model (or a view without a carried head size) estimates its own,
    as a first frame does, at the cost of a second association.

    ``options.seed_min_score`` holds for carried frames only: a first frame grows every pair seed (its first
    associations run at the run's wide bands, without the crowd's heights, where a seed's own score says less, and
    its self-calibration turns small changes of its groups into other shifts).

    ``options.pixel_sigma`` None: the detector's noise is the crowd's. A first frame starts from ``earlier``'s or
    ``START_PIXEL_SIGMA``, and is associated again from the start (its self-calibration's path depends on the
    noise) with the noise its confident persons show, while that is more than ``NOISE_TOLERANCE`` off, at most
    ``MAX_NOISE_RESTARTS`` times; a carried frame takes ``earlier``'s."""
    sigma = options.pixel_sigma or (earlier.pixel_sigma if earlier is not None else None) or START_PIXEL_SIGMA
    if carried or options.pixel_sigma is not None:
        result, _ = _associate_views(views, dataclasses.replace(options, pixel_sigma=sigma), carried, earlier,
                                     check_noise=False)
        assert result is not None  # without the noise's check, every association gives its result
        return result
    initial = list(views)
    for restart in range(MAX_NOISE_RESTARTS + 1):
        views[:] = initial
        result, noise = _associate_views(views, dataclasses.replace(options, pixel_sigma=sigma), carried, earlier,
                                         check_noise=restart < MAX_NOISE_RESTARTS)
        if result is not None:
            return result
        assert noise is not None  # no result: the noise it found
        logger.info("the detections' noise: %.2f px per coordinate, not the %.2f px assumed: associated again",
                    noise, sigma)
        sigma = round(noise, 2)
    raise AssertionError("the last association checks no noise: it returns its result")


def _associate_views(views: list[View], options: AssociateOptions, carried: bool, earlier: FrameResult | None,
                     check_noise: bool) -> tuple[FrameResult | None, float | None]:
    """:func:`associate_views` with ``options.pixel_sigma`` given; ``check_noise``: returns (None, the noise) as soon
    as its self-calibrated persons show a noise more than ``NOISE_TOLERANCE`` off it."""
    names = [v.name for v in views]
    if not carried:
        options = dataclasses.replace(options, seed_min_score=None)
    given = options
    start = earlier.detection_probability if earlier is not None else None
    options = dataclasses.replace(options, detection_probability=options.detection_probability or start
                                  or START_DETECTION)
    if options.height_prior is None and earlier is not None:
        options = dataclasses.replace(options, height_prior=earlier.height_prior)
    if options.head_radius_m is None and earlier is not None and earlier.head_radius_m is not None:
        options = dataclasses.replace(options, head_radius_m=earlier.head_radius_m)
    model = _carried_appearance(views, options, earlier) if carried else None
    # a carried frame's persons are near the frame before's (the same cameras, a fraction of a second later)
    before = (earlier.points, earlier.covariances, seen_before(earlier.views, earlier.members, names)) \
        if carried and earlier is not None and options.walk_m is not None and len(earlier) else None
    state = _solve(views, options, model, earlier=before)
    count = len(_confident(state[1], state[4], options))
    pending: ViewCorrection | None = None
    if carried:
        # The views hold earlier frames' shifts: associate once with them, and pool this frame's groups into the
        # shifts for the next frame (the frame is not associated again: the next one gains, at no extra cost).
        confident = _confident(state[1], state[4], options)
        if options.self_calibration_rounds > 0 and len(confident) >= options.self_calibration_min_members:
            pending = estimate_view_shifts(state[0], confident, options, pooled=True)
    elif options.self_calibration_rounds > 0 and len(views) >= 3:
        # Two starts, each associated once and the one with more confident groups taken: the pairs' distances alone,
        # and with the candidates' heights (neither finds the shifts on every crowd)
        best: tuple | None = None
        offsets = _epipolar_offsets(state[0])  # the same candidates for both
        for heights in (False, True):
            correction, gain = pairwise_view_shifts(state[0], options, heights=heights, offsets=offsets)
            trial = _corrected(views, correction, options)
            tried = _solve(trial, options)
            tried_count = len(_confident(tried[1], tried[4], options))
            logger.info("pairwise shifts (%s, log-likelihood gain %.1f): %d confident groups against %d on the run's "
                        "poses", "with the heights" if heights else "distances", gain, tried_count, count)
            if best is None or tried_count > best[2]:
                best = (trial, tried, tried_count)
        assert best is not None  # the loop above runs twice
        trial, tried, tried_count = best
        # Kept only when the shifted views hold enough confident groups to re-estimate the shifts from: a handful
        # more than none is chance, not evidence.
        if tried_count > count and tried_count >= options.self_calibration_min_members:
            views[:] = trial
            state, count = tried, tried_count
    for _ in range(0 if carried else options.self_calibration_rounds):
        confident = _confident(state[1], state[4], options)
        if len(confident) < options.self_calibration_min_members:
            logger.info("%d confident groups: too few to correct the views", len(confident))
            break
        trial = _corrected(views, estimate_view_shifts(state[0], confident, options), options)
        tried = _solve(trial, options)
        tried_count = len(_confident(tried[1], tried[4], options))
        logger.info("shifts from %d groups: %d confident groups after", len(confident), tried_count)
        if tried_count < count:
            break
        views[:] = trial
        state, count, grew = tried, tried_count, tried_count > count
        if not grew:
            break  # converged: the crowd holds no more confident groups to learn from
    if check_noise and count >= MIN_RATE_GROUPS:
        noise = _detection_noise(state, options)
        assert options.pixel_sigma is not None  # associate_views gives it
        if noise is not None and abs(noise / options.pixel_sigma - 1.0) > NOISE_TOLERANCE:
            return None, noise
    if not carried:
        _warn_beyond_band(views)
        # The crowd's own detection probability and heights, once, from the persons of the corrected views:
        # associated once more where they differ from what the association assumed.
        estimated = _crowd_rates(state, options, given)
        if estimated != options:
            options = estimated
            state = _solve(views, options, frame=state[0])
    if model is None and options.appearance and views and all(v.grey is not None for v in views):
        # The crowd's own appearance model, from this association's confident groups: associated once more with it.
        model = appearance_model(state, views, options)
        if model is not None:
            state = _solve(views, options, model, frame=state[0], earlier=before)
    frame, members, points, covariance, scores, positive = state
    total = int(frame.offsets[-1])
    covariance = covariance + _centre_term(views, members)
    local = np.where(members >= 0, members - frame.offsets[:-1][None], -1)
    order = np.lexsort((points[:, 1], points[:, 0]))
    logger.info("%d persons from %d detections in %d views (%d hypotheses)", len(order), total, len(views), positive)
    # The rates this frame used carry to the next frame as they are: the persons found under a height prior are
    # already shaped by it, so estimating it again from them would narrow it frame by frame.
    used = {v.name: v.shift_px.copy() for v in views}
    bands = {v.name: v.band_sigma_px if v.band_sigma_px is not None else v.sigma_pose_px for v in views}
    if pending is not None:  # after the frame's own record, which keeps the shifts its persons were found with
        _apply_correction(views, pending, options)
    return FrameResult(names, points[order], covariance[order], scores[order], local[order],
                       options.detection_probability, options.height_prior, model,
                       options.head_radius_m if state[0].log_radius is not None else None, used, bands,
                       options.view_occlusion, options.pixel_sigma), None


START_DETECTION = 0.7  # the detection probability assumed until the frame's persons say otherwise
START_PIXEL_SIGMA = 1.0  # the detector's noise (px) a first frame starts from (assumed low: benchmarks/README.md)
NOISE_TOLERANCE = 0.1  # a first frame is associated again from the start where its persons' noise is this far off
MAX_NOISE_RESTARTS = 3
MIN_RATE_GROUPS = 20  # persons needed to estimate the detection probability or the heights from


def _detection_noise(state: tuple, options: AssociateOptions) -> float | None:
    """The detector's noise per coordinate (px) from the association ``state``'s confident persons (three views or
    more scoring above ``self_calibration_min_score``): their members' residuals about their points."""
    frame, members, points, _covariance, scores, _ = state
    confident = (np.sum(members >= 0, axis=1) >= 3) & (scores > options.self_calibration_min_score)
    if confident.sum() < MIN_RATE_GROUPS:
        return None
    return detection_noise(frame.residuals(members[confident], points[confident]) * frame.noise[None] ** 2)


def _crowd_rates(state: tuple, options: AssociateOptions, given: AssociateOptions) -> AssociateOptions:
    """``options`` with the detection probability and the height prior the association ``state`` found, each only
    where ``given`` leaves it to the crowd and enough persons say it (rounded: a change below that is noise)."""
    frame, members, points, covariance, scores, _ = state
    size = np.sum(members >= 0, axis=1)
    changes: dict = {}
    if given.detection_probability is None and len(members) >= MIN_RATE_GROUPS:
        p = truncated_binomial_p(size, np.maximum(frame.seen(points), size))
        if p is not None:
            changes["detection_probability"] = round(p, 2)
    confident = (size >= 3) & (scores > options.self_calibration_min_score)
    if given.height_prior is None and confident.sum() >= MIN_RATE_GROUPS:
        z = points[confident, 2]
        own = float(np.median(covariance[confident, 2, 2]))  # the score adds each point's own on top
        sigma = math.sqrt(max(float(np.var(z)) - own, 0.02 ** 2))
        changes["height_prior"] = (round(float(np.mean(z)), 2), round(sigma, 2))
    heights = changes.get("height_prior", options.height_prior)
    if given.visibility and given.occlusion is None and heights is not None and confident.sum() >= MIN_RATE_GROUPS:
        # fitted on the persons found under one probability for every view, the frame associated again with it
        changes["occlusion"] = fit_occlusion(frame.views, frame.centres, members, points, confident, heights)
    if given.head_radius_m is None and frame.log_radius is not None and confident.sum() >= MIN_RATE_GROUPS:
        # each member's radius times its distance over the focal: the person's R (the median: robust to a wrong one)
        rows, cols = np.nonzero(members[confident] >= 0)
        det = members[confident][rows, cols]
        dist = np.linalg.norm(points[confident][rows] - frame.centres[cols], axis=1)
        log_r = frame.log_radius[det] + np.log(dist) - np.log(frame.focals[cols])
        changes["head_radius_m"] = round(float(np.exp(np.median(log_r))), 3)
    if changes:
        logger.info("the crowd's rates: %s", changes)
    return dataclasses.replace(options, **changes)


def _carried_appearance(views: list[View], options: AssociateOptions,
                        earlier: FrameResult | None) -> AppearanceModel | None:
    """``earlier``'s appearance model, each view's detections described at its carried head size; None (and no view
    described) where the cue is off, an image unreadable, there is no earlier model or a view carries no head size."""
    model = earlier.appearance if earlier is not None else None
    if model is None or not options.appearance or not views \
            or any(v.grey is None or v.head_px is None for v in views):
        return None
    for view in views:
        view.descriptor = describe(view.grey, view.xy, view.head_px)  # type: ignore[arg-type]
    return model


def appearance_model(state: tuple, views: list[View], options: AssociateOptions) -> AppearanceModel | None:
    """Each view's detections described at the apparent head size of its persons (the median depth of the persons
    it sees in ``state``), and the same-against-different model from ``state``'s confident groups."""
    frame, members, points = state[0], state[1], state[2]
    for v, view in enumerate(views):
        seen = members[:, v] >= 0
        if not seen.any() or view.grey is None:
            view.descriptor = None
            continue
        _, z = view.project(points[seen])
        view.head_px = head_radius_px(view.focal, float(np.median(z)))
        view.descriptor = describe(view.grey, view.xy, view.head_px)
    if not all(v.descriptor is not None for v in views):
        logger.info("appearance: a view sees no person of the first association; left out")
        return None
    descriptors = np.concatenate([v.descriptor for v in views])  # type: ignore[misc]
    return estimate(descriptors, frame.view_of, _confident(members, state[4], options))
