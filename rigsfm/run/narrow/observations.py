"""Narrow observations (``rigsfm run --narrow auto|on|off``): synchronised narrow images matched with pose-guided,
height-aware search after a first adjustment, and the matches added to the adjustment as observations.

Narrow images of different rigs with the same frame name were taken at the same instant, so a crowd, static within
that instant, is one scene in both: matches between them observe the narrow cameras (and E^sl) directly. Wide-only
mapping cannot find them cheaply (the views are tens of degrees apart and magnified), but once the network is
adjusted the search is short:

1. **Features**: the self-check's (:mod:`rigsfm.run.checks.guided`, step 1): OpenCV SIFT on each narrow image of the
   first ``max_frames`` synchronised frames, reduced to about ``sift_size`` px, and on j warped into i's view through
   the plane at ``warp_height_m`` (the floor) in the floor frame: without the warp the views, tens of degrees apart,
   give few comparable descriptors (benchmarks/README.md, "Narrow observations").
2. **Height-aware guidance**: keypoint j is a candidate for keypoint i where it lies within ``tolerance`` px of the
   part of i's epipolar line between the floor and ``self_check.TOP_HEIGHT_M`` (a plane sweep over every height
   a person can reach, in the floor frame; the same segment the association of persons searches); then Lowe's
   ratio among each keypoint's candidates and mutual best matches.
3. **Decision** (``auto``): the narrow images carry usable texture when at least ``MIN_TEXTURED_SHARE`` of the
   overlapping pairs (and ``MIN_TEXTURED_PAIRS``) give ``MIN_PAIR_MATCHES`` matches each; featureless views give
   none, and then nothing changes (the result is the adjustment without narrow observations, bit for bit).
4. **Observations**: matches are joined into tracks across pairs (one keypoint per image), every ``HOLD_OUT_EVERY``-th
   match of each pair (ordered by its pixel in i: deterministic) is held out, the rest triangulated and added to
   the model as 3D points of the frame (at most ``MAX_PAIR_MATCHES`` per pair); the adjustment runs again from the adjusted model, with the calibration
   priors, and its robust loss and outlier rounds judge them like any other observation.
5. **Checks**: the held-out matches never enter the adjustment; their distances from the delivered epipolar lines,
   next to the band, give a verdict per pair (``ok`` when their 95th percentile is within the band plus
   ``self_check.KEYPOINT_NOISE_PX``), independent of what the adjustment fitted. The self-check runs as before on
   all its matches, with the features found here (the same images, SIFT and warp): most of its matches are also
   found here, so it is not independent of the adjustment (leaving out the keypoints the adjustment used would keep
   the ones this search rejected, and measure those).

Where no pair is textured through the floor warp (a crowd of 3D persons: heads off the floor), heads are matched
instead (:mod:`rigsfm.run.narrow.heads`) and enter through the same tracks, adjustment and held-out check.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.associate.sync import NOT_A_RECORDING, SyncCheck, not_synchronised
from rigsfm.associate.sync import describe as describe_timing
from rigsfm.core.summary import (
    BANDS_WIDE_ONLY,
    BANDS_WITH_NARROW,
    HeldOutCheckSummary,
    NarrowObservationsSummary,
    NarrowPairSummary,
)
from rigsfm.run.checks.guided import (
    band_candidates,
    epipolar_segments,
    guided_matches,
    load_narrow,
    overlapping_pairs,
    pair_features,
)
from rigsfm.run.checks.self_check import frames_most_rigs_share, synchronised_frames
from rigsfm.run.checks.sync import frames_by_time
from rigsfm.run.deliver import fundamental_matrix
from rigsfm.run.options import NarrowMode, SelfCheckOptions

logger = logging.getLogger(__name__)

# Lateral search tolerance around i's epipolar line, as a share of the narrow image's width: the first adjustment's
# epipolar error with a realistic rigs.yaml is a few pixels.
TOLERANCE_FRACTION = 0.008
MIN_PAIR_MATCHES = 20  # a pair with this many guided matches sees texture
MAX_SPREAD_FRACTION = 0.25  # ... when they are concentrated on the epipolar lines (PairMatches.textured)
MIN_TEXTURED_SHARE = 0.25  # of the overlapping pairs
MIN_TEXTURED_PAIRS = 2
HOLD_OUT_EVERY = 5  # every 5th match of a pair (20 %) is kept out of the adjustment
# Matches kept per pair, evenly over the pair's matches ordered by pixel: a textured pair gives hundreds, whose
# second adjustment costs more than they add, and whose errors are not independent (SIFT on warped views).
MAX_PAIR_MATCHES = 150
MIN_HELD_OUT = 10  # held-out matches a pair needs for a verdict
# Candidate pairs one pair's search compares at most. Without a floor frame whole epipolar lines are searched, and
# beyond it every k-th keypoint of i is (guided.BandCandidates.thinned: each kept keypoint's whole line, so its ratio
# test is unchanged): a pair keeps at most MAX_PAIR_MATCHES matches and needs MIN_PAIR_MATCHES of a full search, so a
# share of them measures its texture as well; a floor-frame search (height segments) stays far below it.
MAX_PAIR_CANDIDATES = 250_000
MIN_TRIANGULATION_DEG = 1.0  # rays closer than this make no point


@dataclass
class PairMatches:
    frame: str
    i: str
    j: str
    xy_i: np.ndarray  # raw COLMAP pixels
    xy_j: np.ndarray
    held_out: np.ndarray  # bool per match: kept out of the adjustment
    tolerance_px: float = 0.0  # of the search
    found: int = 0  # guided matches before MAX_PAIR_MATCHES
    in_adjustment: bool = False  # its matches (less the held-out ones) entered the adjustment
    spread_px: float | None = None  # robust sigma of the matches' signed distances from the epipolar lines
    searched: float = 1.0  # share of i's keypoints searched (MAX_PAIR_CANDIDATES)

    @property
    def textured(self) -> bool:
        """Matches enough (MIN_PAIR_MATCHES of a full search: that share of them where a part of i's keypoints was
        searched), and concentrated on the epipolar lines: false matches spread evenly over the search band (a robust
        sigma of tolerance / 1.7), true ones within the geometry's error."""
        return self.found >= MIN_PAIR_MATCHES * self.searched and self.spread_px is not None and \
            self.spread_px <= MAX_SPREAD_FRACTION * self.tolerance_px

    @property
    def matches(self) -> int:
        return len(self.xy_i)


@dataclass
class HeldOutCheck:
    i: str
    j: str
    band_px: float | None
    held_out: int
    median_px: float | None = None
    p95_px: float | None = None
    within_band: float | None = None
    verdict: str = "too few matches"

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


@dataclass
class NarrowObservations:
    """What ``--narrow`` decided and did (summary.json ``narrow_observations``)."""

    asked: str
    used: bool
    reason: str
    pairs: list[PairMatches] = field(default_factory=list)
    points_added: int = 0
    observations_added: int = 0
    held_out: int = 0
    seconds: float = 0.0
    held_out_checks: list[HeldOutCheck] = field(default_factory=list)
    # (i, j) -> the pair's SIFT features (the self-check reuses them: the same images, SIFT and warp as its own)
    features: dict = field(default_factory=dict, repr=False)
    matched_by: str = "floor warp"  # or "heads" (rigsfm.run.narrow.heads)
    head_persons: int | None = None  # confident persons of the heads' association, where it ran
    head_candidates: int | None = None
    head_verdicts: int = 0  # self-check pairs given a verdict by their head matches
    head_check_pairs: list[PairMatches] = field(default_factory=list, repr=False)  # the heads' self-check matches
    head_sigma_px: float | None = None  # the heads' centres' noise per coordinate their observations are weighed at
    # point3D_id -> that noise, per point the heads added (the second adjustment's point_sigmas)
    point_sigmas: dict[int, float] = field(default_factory=dict, repr=False)
    head_timing: SyncCheck | None = None  # the heads' frame-offset check (rigsfm.run.narrow.timing), where it ran

    @property
    def warnings(self) -> list[str]:
        """A rig the heads name off in time (its heads were kept out of the adjustment)."""
        late = self.head_timing.named if self.head_timing is not None else {}
        lines = ", ".join(f"'{r}: {o}'" for r, o in sorted(late.items()))
        return [not_synchronised(late, "its heads are kept out of the narrow adjustment (they lie where its walkers "
                                       "will be, not where the other views see them); give --frame-offsets FILE "
                                       f"({lines}) to pair its frames by time")] if late else []

    @property
    def bands_from(self) -> str:
        """The adjustment whose bands are delivered: the one with these observations where they are matches through
        the floor, whose noise is modelled per pair (rigsfm.run.adjustment.correlated); the first one where they are
        heads: weighed at their own noise (rigsfm.run.narrow.heads, step 6) they hold the poses better, but their
        adjustment's band still fell short of a 3D crowd's true errors (benchmarks/README.md)."""
        return BANDS_WITH_NARROW if self.used and self.matched_by != "heads" else BANDS_WIDE_ONLY

    def line(self) -> str:
        """The terminal's line."""
        return describe_record(self.summary())

    def summary(self) -> NarrowObservationsSummary:
        """summary.json's ``narrow_observations``."""
        return NarrowObservationsSummary(
            asked=self.asked, used=self.used, reason=self.reason, seconds=round(self.seconds, 3),
            points_added=self.points_added, observations_added=self.observations_added,
            held_out_matches=self.held_out,
            pairs=[NarrowPairSummary(frame=p.frame, i=p.i, j=p.j, found=p.found, matches=p.matches,
                                     spread_px=None if p.spread_px is None else round(p.spread_px, 3),
                                     search_px=round(p.tolerance_px, 3), textured=p.textured,
                                     in_adjustment=p.in_adjustment, searched=round(p.searched, 4),
                                     held_out=int(p.held_out.sum()) if p.in_adjustment else 0)
                   for p in self.pairs],
            held_out_check=[HeldOutCheckSummary(**c.to_dict()) for c in self.held_out_checks],
            bands=self.bands_from if self.used else None, matched_by=self.matched_by, head_persons=self.head_persons,
            head_candidates=self.head_candidates, head_verdicts=self.head_verdicts,
            head_sigma_px=None if self.head_sigma_px is None else round(self.head_sigma_px, 3),
            head_frame_offsets=None if self.head_timing is None else self.head_timing.to_dict())


def describe_record(record: NarrowObservationsSummary) -> str:
    """One line on a ``--narrow`` record (the terminal's)."""
    line = (f"narrow observations {'used' if record.used else 'not used'} (--narrow {record.asked}): "
            f"{record.reason}")
    if record.used:
        verdicts = [c.verdict for c in record.held_out_check]
        line += (f"; {record.observations_added} observations of {record.points_added} points added, "
                 f"{record.held_out_matches} matches held out; bands: {record.bands}")
        if verdicts:
            rest = len(verdicts) - verdicts.count("ok") - verdicts.count("failed")
            line += (f"; held-out check: {verdicts.count('ok')} ok, {verdicts.count('failed')} failed, "
                     f"{rest} without verdict")
    timing = record.head_frame_offsets
    if timing and timing.get("skipped") != NOT_A_RECORDING:  # a recording's heads timed its rigs, or could not
        line += "; heads' " + describe_timing(timing)
    return line


def _j_from_i(image_i: pycolmap.Image, image_j: pycolmap.Image) -> pycolmap.Rigid3d:
    return image_j.cam_from_world() * image_i.cam_from_world().inverse()


def find_matches(floor_model: pycolmap.Reconstruction, image_dir: Path, options: SelfCheckOptions | None = None,
                 *, floor_frame: bool = True, offsets: dict[str, int] | None = None,
                 features: dict | None = None) -> list[PairMatches]:
    """Guided matches (module docstring, steps 1-2) of every overlapping synchronised narrow pair of the first
    ``options.max_frames`` frames; ``floor_model`` is the adjusted model in the floor frame (z up, metres); without
    ``floor_frame`` (no floor found) every narrow pair is searched along the whole epipolar line; with ``offsets``
    (rig -> frames, --frame-offsets FILE) frames are paired by time (rigsfm.run.checks.sync.frames_by_time); ``features``
    (a dict) receives each pair's features, for the self-check to reuse."""
    opt = options or SelfCheckOptions()
    offsets = {r: int(o) for r, o in (offsets or {}).items() if o}
    if offsets:
        frames = frames_by_time(floor_model, offsets)
    else:
        frames = synchronised_frames(floor_model)
    found = []
    for frame in frames_most_rigs_share(frames, opt.max_frames):  # the self-check's frames: its features reused
        images = frames[frame]
        pairs = overlapping_pairs(floor_model, images, floor_frame)
        loaded = {name: load_narrow(floor_model.find_image_with_name(name), Path(image_dir),
                              opt.warp_height_m if floor_frame else None, opt.sift_size)
                  for name in sorted({n for p in pairs for n in p})}
        for name_i, name_j in pairs:
            first, second = loaded[name_i], loaded[name_j]
            if first is None or second is None or first.features is None or second.features is None:
                found.append(_empty(frame, name_i, name_j))
                continue
            fi, fj = pair_features(first, second)  # j warped into i's view (floor frame)
            if features is not None and fi is not None and fj is not None:
                features[(name_i, name_j)] = (fi, fj)
            if fi is None or fj is None or len(fi.xy) < 2:
                found.append(_empty(frame, name_i, name_j))
                continue
            image_i, image_j = first.image, second.image
            # a model's images have their cameras
            f_ji = fundamental_matrix(_j_from_i(image_i, image_j), image_i.camera, image_j.camera)  # type: ignore[arg-type]
            lines = np.c_[fi.undistorted, np.ones(len(fi.undistorted))] @ f_ji.T
            segments = epipolar_segments(image_i, image_j, fi.undistorted, floor_frame)
            tolerance = TOLERANCE_FRACTION * image_j.camera.width  # type: ignore[union-attr]
            every = band_candidates(f_ji, lines, fj.undistorted, segments, tolerance)
            candidates = every.thinned(MAX_PAIR_CANDIDATES)
            searched = 1.0
            if candidates is not every:  # the share of i's keypoints with candidates that kept theirs
                searched = len(np.unique(candidates.a)) / len(np.unique(every.a))
                logger.info("narrow observations %s -> %s: %d candidate pairs, %.0f %% of the keypoints searched "
                            "(%d pairs)", name_i, name_j, len(every.a), 100 * searched, len(candidates.a))
            matches = guided_matches(fi, fj, candidates.a, candidates.b)
            if len(matches) == 0:
                found.append(_empty(frame, name_i, name_j))
                continue
            hj = np.c_[fj.undistorted[matches[:, 1]], np.ones(len(matches))]
            line = lines[matches[:, 0]]
            signed = np.einsum("ij,ij->i", line, hj) / np.linalg.norm(line[:, :2], axis=1)
            spread = 1.4826 * float(np.median(np.abs(signed - np.median(signed))))
            xy_i, xy_j = fi.xy[matches[:, 0]], fj.xy[matches[:, 1]]
            order = np.lexsort((xy_i[:, 0], xy_i[:, 1]))
            if len(order) > MAX_PAIR_MATCHES:
                order = order[np.linspace(0, len(order) - 1, MAX_PAIR_MATCHES).round().astype(int)]
                xy_i, xy_j = xy_i[order], xy_j[order]
                order = np.arange(len(order))  # the kept matches, already in pixel order
            held = np.zeros(len(xy_i), bool)
            held[order[::HOLD_OUT_EVERY]] = True
            found.append(PairMatches(frame, name_i, name_j, xy_i, xy_j, held, found=len(matches),
                                     tolerance_px=tolerance, spread_px=spread, searched=searched))
            logger.info("narrow observations %s -> %s: %d guided matches, lateral spread %.2f of %.2f px",
                        name_i, name_j, len(matches), spread, tolerance)
    return found


def _empty(frame: str, i: str, j: str) -> PairMatches:
    return PairMatches(frame, i, j, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, bool))


def decide(asked: NarrowMode, pairs: list[PairMatches]) -> tuple[bool, str]:
    """Whether the matches enter the adjustment (module docstring, step 3), and why."""
    textured = sum(p.textured for p in pairs)
    counts = (f"{textured} of {len(pairs)} overlapping synchronised narrow pairs give >= {MIN_PAIR_MATCHES} guided "
              "matches concentrated on the epipolar lines")
    if asked == NarrowMode.ON:
        return bool(pairs) and any(p.matches for p in pairs), f"asked (--narrow on); {counts}"
    enough = textured >= max(MIN_TEXTURED_PAIRS, MIN_TEXTURED_SHARE * len(pairs))
    return enough, (f"the narrow images carry usable texture: {counts}" if enough
                    else f"the narrow images carry no usable texture: {counts}")


Key = tuple[str, float, float]  # image name, pixel (rounded): a keypoint of one image, whichever pair found it


def _key(name: str, xy: np.ndarray) -> Key:
    return name, round(float(xy[0]), 3), round(float(xy[1]), 3)


def _tracks(pairs: list[PairMatches]) -> list[list[Key]]:
    """Matches not held out, joined across pairs into tracks of keypoints (a keypoint of i is the same pixel in
    every pair; j's come from a warp per pair); a track that would hold two keypoints of one image falls apart
    into its matches, each a two-view track (one of them is wrong, and the adjustment's rounds judge which)."""
    parent: dict[Key, Key] = {}

    def find(x: Key) -> Key:
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    edges = []
    for pair in pairs:
        for xy_i, xy_j, held in zip(pair.xy_i, pair.xy_j, pair.held_out, strict=True):
            if not held:
                a, b = _key(pair.i, xy_i), _key(pair.j, xy_j)
                edges.append((a, b))
                parent[find(a)] = find(b)
    groups: dict[Key, list[Key]] = {}
    for node in list(parent):
        groups.setdefault(find(node), []).append(node)
    consistent = {root for root, members in groups.items() if len({m[0] for m in members}) == len(members)}
    tracks = [members for root, members in groups.items() if root in consistent]
    tracks += [[a, b] for a, b in edges if find(a) not in consistent]
    return tracks


def _triangulate(tracks: list[list[Key]], model: pycolmap.Reconstruction,
                 by_name: dict[str, int]) -> list[np.ndarray | None]:
    """Each track's point, nearest its rays in the least-squares sense (the N-view midpoint, all tracks at once:
    thousands of tracks through pycolmap's objects one by one took seconds); None where the widest angle between
    its rays is below ``MIN_TRIANGULATION_DEG``, a ray is not finite, or the point lies behind a camera."""
    track_of = np.repeat(np.arange(len(tracks)), [len(t) for t in tracks])
    keys = [key for track in tracks for key in track]
    names = sorted({key[0] for key in keys})
    rays = np.zeros((len(keys), 3))
    rotations, translations = np.zeros((len(keys), 3, 3)), np.zeros((len(keys), 3))
    for name in names:  # per image: its rays at once
        rows = np.array([k for k, key in enumerate(keys) if key[0] == name])
        image = model.image(by_name[name])
        pose = image.cam_from_world()
        xy = np.array([[keys[k][1], keys[k][2]] for k in rows])
        rays[rows, :2] = np.asarray(image.camera.cam_from_img(xy), dtype=np.float64)  # type: ignore[union-attr]
        rays[rows, 2] = 1.0
        rotations[rows], translations[rows] = np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)
    finite = np.isfinite(rays).all(axis=1)
    rays[~finite] = [0.0, 0.0, 1.0]
    directions = np.einsum("nji,nj->ni", rotations, rays / np.linalg.norm(rays, axis=1, keepdims=True))
    centres = -np.einsum("nji,nj->ni", rotations, translations)
    projector = np.eye(3) - directions[:, :, None] * directions[:, None, :]
    a, b = np.zeros((len(tracks), 3, 3)), np.zeros((len(tracks), 3))
    np.add.at(a, track_of, projector)
    np.add.at(b, track_of, np.einsum("nij,nj->ni", projector, centres))
    first = directions[np.r_[0, np.cumsum([len(t) for t in tracks])[:-1]]]
    angle = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", directions, first[track_of]), -1.0, 1.0)))
    widest = np.zeros(len(tracks))
    np.maximum.at(widest, track_of, angle)
    ok = widest >= MIN_TRIANGULATION_DEG
    np.logical_and.at(ok, track_of, finite)
    points = np.full((len(tracks), 3), np.nan)
    points[ok] = np.linalg.solve(a[ok], b[ok][:, :, None])[:, :, 0]
    depth = np.einsum("nij,nj->ni", rotations, points[track_of])[:, 2] + translations[:, 2]
    np.logical_and.at(ok, track_of, depth > 0)
    return [points[t] if ok[t] else None for t in range(len(tracks))]


def add_observations(model: pycolmap.Reconstruction, pairs: list[PairMatches]
                     ) -> tuple[pycolmap.Reconstruction, int, int]:
    """A copy of ``model`` with the tracks of ``pairs`` (held-out matches excluded) as 3D points; their pixels are
    appended to each image's 2D points. Returns (copy, points added, observations added)."""
    copy = pycolmap.Reconstruction(model)
    by_name = {im.name: im.image_id for im in copy.images.values()}
    appended: dict[str, list[np.ndarray]] = {}
    base: dict[str, int] = {}
    observations = points = 0
    tracks_of_points: list[tuple[np.ndarray, pycolmap.Track]] = []
    tracks = _tracks(pairs)
    for track, point in zip(tracks, _triangulate(tracks, copy, by_name) if tracks else [], strict=True):
        if point is None:
            continue
        pixels = [np.array([x, y]) for _, x, y in track]
        colmap_track = pycolmap.Track()
        for (name, _, _), xy in zip(track, pixels, strict=True):
            base.setdefault(name, copy.image(by_name[name]).num_points2D())
            colmap_track.add_element(by_name[name], base[name] + len(appended.setdefault(name, [])))
            appended[name].append(xy)
        points += 1
        observations += len(track)
        tracks_of_points.append((point, colmap_track))
    for name, xys in appended.items():
        image = copy.image(by_name[name])
        image.points2D = pycolmap.Point2DList(
            list(image.points2D) + [pycolmap.Point2D(np.asarray(xy, dtype=np.float64)) for xy in xys])
    for point, colmap_track in tracks_of_points:
        copy.add_point3D(point, colmap_track)
    return copy, points, observations
