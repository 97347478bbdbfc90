"""3D persons standing and walking on the homogeneous centre disc, their exact ray casting, and their truth.

A person is a body (a vertical elliptic cylinder ``BODY_HALF`` = 0.225 x 0.15 m, shoulders along its local x, from
the floor up to the shoulders), a neck (a thin cylinder) and a head (a sphere of ``HEAD_RADIUS``) whose top is at
the person's height (uniform in ``HEIGHT_RANGE``). Trousers, top, neck and head each have one grey level per person,
shaded by the arena's light: a crowd seen from 15-20 m. ``SceneOptions.persons_per_m2`` persons stand on the disc
(``centre_radius`` less ``DISC_MARGIN``), centres at least ``person_separation`` apart.

Time is counted in frames: frame ``k`` of a rig with offset ``o`` (``SceneOptions.frame_offsets``) is taken at
``(k + o) * frame_period_s`` seconds. Each person walks a smooth random walk (own speed in ``SPEED_RANGE``, heading
diffusing, steered back from the disc's edge) simulated in ``substeps`` steps per frame period, forward from the
state at time 0 for positive times and backward for negative ones, so the positions at a given time do not depend
on which frames or offsets a dataset asks for; after each step overlapping persons are pushed apart. Integer times
(in frames) are simulated states exactly; other times interpolate the two nearest steps linearly.

Truth, beside the ground truth (``render_dataset`` writes it when there are persons)::

  persons/heads.csv        image,x,y,person,visible,visible_fraction: one row per image and per head whose centre
                           projects inside the image (COLMAP pixels, ``rigsfm.core.geometry.project_world``, which
                           rejects points beyond the lens model's monotonic range); visible = 1 when the ray to the
                           head centre first meets that head; visible_fraction = the share of
                           ``VISIBILITY_SAMPLES`` points spread over the head's silhouette disc whose rays first meet
                           that head (occlusion only: the image border does not count)
  persons/frame0000.json   {"frame": k, "period_s": P, "head_radius_m": r,
                            "rigs": {"rig01": {"offset_frames": o, "time_s": t, "instant": i}, ...},
                            "instants": [{"time_s": t, "heads": [[x, y, z], ...]}, ...]}  (world metres,
                           heads[person] is that person's head centre; rigs captured at one time share an instant)

:func:`read_person_truth` reads both back.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from rigsfm.core.errors import InputError

if TYPE_CHECKING:
    from rigsfm.synth.options import SceneOptions

logger = logging.getLogger(__name__)

BODY_HALF = (0.225, 0.15)  # semi-axes (m) of the body's ellipse: across the shoulders, front to back
HEAD_RADIUS = 0.11
NECK_RADIUS = 0.055
NECK_LENGTH = 0.03  # between the shoulders and the bottom of the head
LEGS_FRACTION = 0.47  # trousers up to this fraction of the height
HEIGHT_RANGE = (1.5, 1.9)
SPEED_RANGE = (0.5, 1.3)  # m/s, each person's own walking speed
HEADING_DIFFUSION = 0.6  # rad / sqrt(s): how fast a walker's heading wanders
STEP_S = 0.1  # longest simulation step (s)
DISC_MARGIN = 0.5  # persons keep this far inside the homogeneous disc's edge
VISIBILITY_SAMPLES = 19
REACH = float(np.hypot(*BODY_HALF))  # horizontal radius that holds every part of a person
LEGS, TOP, NECK, HEAD = 0, 1, 2, 3  # parts, as Hits.u holds them for person hits


@dataclass(frozen=True)
class Persons:
    """The crowd at one instant: centre on the floor, shoulder-axis angle (rad), height, and greys per part."""

    xy: np.ndarray  # P x 2
    yaw: np.ndarray  # P
    height: np.ndarray  # P
    greys: np.ndarray  # P x 4, by part (LEGS, TOP, NECK, HEAD), in [0, 1]

    def __len__(self) -> int:
        return len(self.height)

    def head_centres(self) -> np.ndarray:
        return np.column_stack([self.xy, self.height - HEAD_RADIUS])

    def shoulders(self) -> np.ndarray:
        return self.height - 2 * HEAD_RADIUS - NECK_LENGTH


@dataclass(frozen=True)
class Crowd:
    """Every person's fixed attributes and simulated trajectory (steps ``first_step`` .. ``first_step + S - 1``)."""

    height: np.ndarray
    greys: np.ndarray
    xy: np.ndarray  # S x P x 2
    yaw: np.ndarray  # S x P
    first_step: int
    substeps: int  # simulation steps per frame period
    period_s: float

    def __len__(self) -> int:
        return len(self.height)

    def at(self, time_frames: float) -> Persons:
        """The crowd at ``time_frames * period_s`` seconds (must lie within the simulated span)."""
        step = time_frames * self.substeps - self.first_step
        low = int(math.floor(step + 1e-9))
        if not 0 <= low < len(self.xy) or (step - low > 1e-9 and low + 1 >= len(self.xy)):
            raise ValueError(f"time {time_frames} frames is outside the simulated span")
        w = step - low
        if w <= 1e-9:
            xy, yaw = self.xy[low], self.yaw[low]
        else:
            xy = (1 - w) * self.xy[low] + w * self.xy[low + 1]
            turn = np.mod(self.yaw[low + 1] - self.yaw[low] + np.pi, 2 * np.pi) - np.pi
            yaw = self.yaw[low] + w * turn
        return Persons(xy.copy(), yaw.copy(), self.height, self.greys)


def parse_frame_offsets(text: str) -> tuple[tuple[str, float], ...]:
    """``"rig02=1,rig05=-2.5"`` -> ``(("rig02", 1.0), ("rig05", -2.5))``; ValueError saying what is wrong."""
    offsets = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        name, sep, value = item.partition("=")
        try:
            number = float(value)
        except ValueError:
            number = math.nan
        if not sep or not name.strip() or not math.isfinite(number):
            raise ValueError(f"frame offset {item!r} is not RIG=FRAMES (e.g. rig02=1,rig05=-2)")
        offsets.append((name.strip(), number))
    names = [name for name, _ in offsets]
    if len(set(names)) != len(names):
        raise ValueError(f"frame offsets name a rig twice: {text!r}")
    return tuple(offsets)


def _greys(rng: np.random.Generator, count: int) -> np.ndarray:
    """Per-person greys: mostly dark or mid clothes, a few light ones; dark to mid hair; skin for the neck."""
    top = np.where(rng.random(count) < 0.5, rng.uniform(0.05, 0.25, count),
                   np.where(rng.random(count) < 0.7, rng.uniform(0.25, 0.6, count), rng.uniform(0.6, 0.9, count)))
    legs = np.where(rng.random(count) < 0.7, rng.uniform(0.06, 0.3, count), rng.uniform(0.3, 0.6, count))
    neck = rng.uniform(0.35, 0.7, count)
    head = np.where(rng.random(count) < 0.75, rng.uniform(0.04, 0.3, count), rng.uniform(0.3, 0.7, count))
    return np.column_stack([legs, top, neck, head])


def _separate(xy: np.ndarray, separation: float, radius: float, iterations: int = 200) -> np.ndarray:
    """Push persons closer than ``separation`` apart (and back inside ``radius``) until none are."""
    xy = xy.copy()
    for _ in range(iterations):
        pairs = cKDTree(xy).query_pairs(separation * (1 - 1e-9), output_type="ndarray")
        if not len(pairs):
            break
        i, j = pairs[:, 0], pairs[:, 1]
        delta = xy[j] - xy[i]
        dist = np.linalg.norm(delta, axis=1)
        degenerate = dist < 1e-9
        delta[degenerate] = [1.0, 0.0]
        dist[degenerate] = 1.0
        push = (delta / dist[:, None]) * ((separation * 1.02 - dist) / 2)[:, None]  # a little extra: fewer rounds
        moves = np.zeros_like(xy)
        np.add.at(moves, i, -push)
        np.add.at(moves, j, push)
        xy += moves
        r = np.hypot(xy[:, 0], xy[:, 1])
        outside = r > radius
        xy[outside] *= (radius / r[outside])[:, None]
    else:
        logger.warning("persons still closer than %.2f m after %d rounds of pushing apart", separation, iterations)
    return xy


def _step(xy: np.ndarray, heading: np.ndarray, speed: np.ndarray, dt: float, rng: np.random.Generator,
          separation: float, radius: float) -> tuple[np.ndarray, np.ndarray]:
    heading = heading + HEADING_DIFFUSION * np.sqrt(dt) * rng.standard_normal(len(heading))
    r = np.hypot(xy[:, 0], xy[:, 1])
    # Near the edge, turn toward the centre (smoothly), so walkers stay on the disc without bouncing.
    inward = np.arctan2(-xy[:, 1], -xy[:, 0])
    pull = np.clip((r - (radius - 1.5)) / 1.5, 0.0, 1.0)
    turn = np.mod(inward - heading + np.pi, 2 * np.pi) - np.pi
    heading = heading + pull * turn * min(1.0, 2.0 * dt)
    xy = xy + (speed * dt)[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    return _separate(xy, separation, radius), heading


def build_crowd(options: SceneOptions, times_frames: list[float] | tuple[float, ...] = (0.0,)) -> Crowd | None:
    """The persons of ``options`` (None without any), simulated over the span that ``times_frames`` need."""
    if options.persons_per_m2 <= 0:
        return None
    radius = options.centre_radius - DISC_MARGIN
    count = int(round(options.persons_per_m2 * np.pi * radius * radius))
    densest = 2.0 / (np.sqrt(3.0) * options.person_separation**2)  # hexagonal packing
    if options.persons_per_m2 > 0.8 * densest:
        raise ValueError(f"persons_per_m2 {options.persons_per_m2} is too dense for person_separation "
                         f"{options.person_separation} m: at most {0.8 * densest:.1f}")
    rng = np.random.default_rng([options.seed, 51])
    r = radius * np.sqrt(rng.random(count))
    phi = rng.uniform(0, 2 * np.pi, count)
    xy0 = _separate(np.column_stack([r * np.cos(phi), r * np.sin(phi)]), options.person_separation, radius,
                    iterations=1000)
    height = rng.uniform(*HEIGHT_RANGE, count)
    greys = _greys(rng, count)
    speed = rng.uniform(*SPEED_RANGE, count)
    heading0 = rng.uniform(-np.pi, np.pi, count)
    substeps = max(1, int(math.ceil(options.frame_period_s / STEP_S - 1e-9)))
    dt = options.frame_period_s / substeps
    first = min(int(math.floor(min(times_frames) * substeps + 1e-9)), 0)
    last = max(int(math.ceil(max(times_frames) * substeps - 1e-9)), 0)
    forward_xy, forward_heading = [xy0], [heading0]
    for k in range(last):
        xy, heading = _step(forward_xy[-1], forward_heading[-1], speed, dt,
                            np.random.default_rng([options.seed, 53, 0, k]), options.person_separation, radius)
        forward_xy.append(xy)
        forward_heading.append(heading)
    backward_xy, backward_heading = [], []
    xy, heading = xy0, heading0 + np.pi  # walking back in time: the same walk, reversed
    for k in range(-first):
        xy, heading = _step(xy, heading, speed, dt, np.random.default_rng([options.seed, 53, 1, k]),
                            options.person_separation, radius)
        backward_xy.append(xy)
        backward_heading.append(heading - np.pi)
    xys = backward_xy[::-1] + forward_xy
    headings = backward_heading[::-1] + forward_heading
    yaw = np.stack(headings) + np.pi / 2  # shoulders across the walking direction
    logger.info("%d persons on the centre disc (%.1f per m2), %d simulation steps", count, options.persons_per_m2,
                len(xys))
    return Crowd(height, greys, np.stack(xys), yaw, first, substeps, options.frame_period_s)


# ---------------------------------------------------------------------------------------------------- ray casting


@dataclass
class PersonHits:
    """The rays (``rows``) that meet a person, with the nearest hit: distance, person, part, unit normal."""

    rows: np.ndarray
    t: np.ndarray
    person: np.ndarray
    part: np.ndarray
    normal: np.ndarray = field(repr=False)


PAIRS_PER_CHUNK = 1_000_000  # ray-person pairs tested at once (memory: ~100 bytes each)


def _candidate_slices(persons: Persons, o: np.ndarray, d: np.ndarray, valid: np.ndarray):
    """Sort the rays into an (azimuth, elevation) grid; per person and grid column, the slice of sorted rays whose
    cells can meet the person's bounding cylinder. Returns (order, slice person, slice start, slice end)."""
    horizontal = np.hypot(d[:, 0], d[:, 1])
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    elevation = np.arctan2(d[:, 2], horizontal)
    mean = d[valid].sum(axis=0)
    reference = float(np.arctan2(mean[1], mean[0])) if np.hypot(mean[0], mean[1]) > 1e-9 else 0.0
    rel = np.mod(azimuth - reference + np.pi, 2 * np.pi) - np.pi
    az_lo, az_hi = float(rel[valid].min()), float(rel[valid].max())
    el_lo, el_hi = float(elevation[valid].min()), float(elevation[valid].max())
    cell = math.sqrt(max(az_hi - az_lo, 1e-6) * max(el_hi - el_lo, 1e-6) * 8.0 / max(int(valid.sum()), 1))
    n_az = min(int((az_hi - az_lo) / cell) + 1, 4096)
    n_el = min(int((el_hi - el_lo) / cell) + 1, 4096)
    az_cell = max(az_hi - az_lo, 1e-12) / n_az * (1 + 1e-9)
    el_cell = max(el_hi - el_lo, 1e-12) / n_el * (1 + 1e-9)
    col = np.minimum(((rel - az_lo) / az_cell).astype(np.int64), n_az - 1)
    row = np.minimum(((elevation - el_lo) / el_cell).astype(np.int64), n_el - 1)
    cell_id = np.where(valid, col * n_el + row, n_az * n_el)  # invalid rays in a last cell no person asks for
    order = np.argsort(cell_id, kind="stable")
    starts = np.concatenate([[0], np.cumsum(np.bincount(cell_id, minlength=n_az * n_el + 1))])

    # Each person's angular box, from the corners of its bounding cylinder (radius REACH, floor to head top).
    dx, dy = persons.xy[:, 0] - o[0], persons.xy[:, 1] - o[1]
    dist = np.hypot(dx, dy)
    near = dist <= REACH + 1e-6  # the camera stands inside the cylinder: every ray
    half = np.arcsin(np.minimum(REACH / np.maximum(dist, 1e-9), 1.0)) + 1e-6
    centre = np.mod(np.arctan2(dy, dx) - reference + np.pi, 2 * np.pi) - np.pi
    corners = [np.arctan2(z - o[2], np.maximum(r, 1e-9)) for z in (np.zeros_like(dist), persons.height + 1e-6)
               for r in (dist - REACH, dist + REACH)]
    lo_el = np.where(near, -np.pi / 2, np.min(corners, axis=0) - 1e-6)
    hi_el = np.where(near, np.pi / 2, np.max(corners, axis=0) + 1e-6)
    lo_az = np.where(near, -np.pi, centre - half)
    hi_az = np.where(near, np.pi, centre + half)
    # Intervals past the +-pi seam continue on its other side: one more interval for those persons.
    person = np.arange(len(persons))
    below, above = lo_az < -np.pi, hi_az > np.pi
    person = np.concatenate([person, person[below], person[above]])
    lo = np.concatenate([np.maximum(lo_az, -np.pi), lo_az[below] + 2 * np.pi, np.full(above.sum(), -np.pi)])
    hi = np.concatenate([np.minimum(hi_az, np.pi), np.full(below.sum(), np.pi), hi_az[above] - 2 * np.pi])
    lo_row = np.clip(np.floor((lo_el[person] - el_lo) / el_cell), 0, n_el - 1).astype(np.int64)
    hi_row = np.clip(np.floor((hi_el[person] - el_lo) / el_cell), -1, n_el - 1).astype(np.int64)
    keep = (hi >= az_lo) & (lo <= az_hi) & (hi_el[person] >= el_lo) & (lo_el[person] <= el_hi) & (hi_row >= lo_row)
    lo_col = np.clip(np.floor((lo[keep] - az_lo) / az_cell), 0, n_az - 1).astype(np.int64)
    hi_col = np.clip(np.floor((hi[keep] - az_lo) / az_cell), 0, n_az - 1).astype(np.int64)
    person, lo_row, hi_row = person[keep], lo_row[keep], hi_row[keep]
    columns = hi_col - lo_col + 1
    entry = np.repeat(np.arange(len(person)), columns)
    col = lo_col[entry] + np.arange(len(entry)) - np.repeat(np.cumsum(columns) - columns, columns)
    start = starts[col * n_el + lo_row[entry]]
    end = starts[col * n_el + hi_row[entry] + 1]
    nonempty = end > start
    return order, person[entry][nonempty], start[nonempty], end[nonempty]


def _pair_hits(persons: Persons, o: np.ndarray, d: np.ndarray, ray: np.ndarray, who: np.ndarray):
    """Nearest hit distance and shape (0 body side, 1 shoulders, 2 neck, 3 head) of each ray-person pair."""
    px, py = persons.xy[who, 0], persons.xy[who, 1]
    cos_y, sin_y = np.cos(persons.yaw[who]), np.sin(persons.yaw[who])
    height = persons.height[who]
    top = height - 2 * HEAD_RADIUS - NECK_LENGTH
    head_z = height - HEAD_RADIUS
    dx, dy, dz = d[ray, 0], d[ray, 1], d[ray, 2]
    rx, ry = o[0] - px, o[1] - py
    lox, loy = cos_y * rx + sin_y * ry, -sin_y * rx + cos_y * ry
    ldx, ldy = cos_y * dx + sin_y * dy, -sin_y * dx + cos_y * dy
    best = np.full(len(ray), np.inf)
    shape = np.full(len(ray), -1, np.int8)

    def keep(t: np.ndarray, code: int) -> None:
        better = (t > 1e-9) & (t < best)
        best[better] = t[better]
        shape[better] = code

    a2, b2 = BODY_HALF[0] ** 2, BODY_HALF[1] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        qa = ldx * ldx / a2 + ldy * ldy / b2
        qb = 2 * (lox * ldx / a2 + loy * ldy / b2)
        qc = lox * lox / a2 + loy * loy / b2 - 1
        t = (-qb - np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
        z = o[2] + t * dz
        keep(np.where((z >= 0) & (z <= top), t, np.inf), 0)
        t = (top - o[2]) / dz
        x, y = lox + t * ldx, loy + t * ldy
        keep(np.where(x * x / a2 + y * y / b2 <= 1, t, np.inf), 1)
        qa = dx * dx + dy * dy
        qb = 2 * (rx * dx + ry * dy)
        qc = rx * rx + ry * ry - NECK_RADIUS**2
        t = (-qb - np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
        z = o[2] + t * dz
        keep(np.where((z >= top) & (z <= head_z), t, np.inf), 2)
        rz = o[2] - head_z
        dd = qa + dz * dz
        hb = rx * dx + ry * dy + rz * dz
        hc = rx * rx + ry * ry + rz * rz - HEAD_RADIUS**2
        keep((-hb - np.sqrt(hb * hb - dd * hc)) / dd, 3)
    return best, shape


def intersect(persons: Persons, origin: np.ndarray, dirs: np.ndarray, bound: np.ndarray | None = None) -> PersonHits:
    """Nearest person hit of every ray ``origin + t * dirs`` nearer than ``bound`` (per ray; default inf): the
    rays that meet nobody before it are left out."""
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    n = len(d)
    best_t = np.full(n, np.inf) if bound is None else np.array(bound, dtype=np.float64)
    best_person = np.full(n, -1, np.int64)
    best_shape = np.full(n, -1, np.int8)
    valid = np.all(np.isfinite(d), axis=1) & (np.linalg.norm(d, axis=1) > 1e-12)
    if len(persons) and valid.any():
        order, who, start, end = _candidate_slices(persons, o, d, valid)
        # Nearest persons first: a ray that already met something nearer than a person's cylinder skips it.
        # (the distance from the eye to the person's bounding cylinder: no hit on the person is nearer)
        across = np.maximum(np.hypot(persons.xy[:, 0] - o[0], persons.xy[:, 1] - o[1]) - REACH, 0.0)
        nearest = np.hypot(across, np.maximum(o[2] - persons.height, np.maximum(-o[2], 0.0)))
        nearest /= max(float(np.linalg.norm(d[valid], axis=1).max()), 1e-12)
        by_distance = np.argsort(nearest[who], kind="stable")
        who, start, end = who[by_distance], start[by_distance], end[by_distance]
        length = end - start
        total = np.cumsum(length)
        first = 0
        while first < len(length):
            base = total[first] - length[first]
            last = max(int(np.searchsorted(total, base + PAIRS_PER_CHUNK, side="right")), first + 1)
            lengths = length[first:last]
            offsets = np.repeat(start[first:last] - (np.cumsum(lengths) - lengths), lengths)
            ray = order[offsets + np.arange(int(lengths.sum()))]
            person = np.repeat(who[first:last], lengths)
            first = last
            open_ = best_t[ray] > nearest[person]
            ray, person = ray[open_], person[open_]
            t, shape = _pair_hits(persons, o, d, ray, person)
            hit = t < best_t[ray]
            ray, person, t, shape = ray[hit], person[hit], t[hit], shape[hit]
            np.minimum.at(best_t, ray, t)
            win = t == best_t[ray]  # of equal distances, the last pair written wins
            best_person[ray[win]] = person[win]
            best_shape[ray[win]] = shape[win]
    rows = np.flatnonzero(best_person >= 0)
    t, person, shape = best_t[rows], best_person[rows], best_shape[rows]
    point = o + t[:, None] * d[rows]
    rel = point - np.column_stack([persons.xy[person], persons.height[person] - HEAD_RADIUS])
    normal = np.zeros((len(rows), 3))
    cos_y, sin_y = np.cos(persons.yaw[person]), np.sin(persons.yaw[person])
    side = shape == 0
    lx = (cos_y * rel[:, 0] + sin_y * rel[:, 1]) / BODY_HALF[0] ** 2
    ly = (-sin_y * rel[:, 0] + cos_y * rel[:, 1]) / BODY_HALF[1] ** 2
    normal[side, 0] = (cos_y * lx - sin_y * ly)[side]
    normal[side, 1] = (sin_y * lx + cos_y * ly)[side]
    normal[shape == 1] = (0.0, 0.0, 1.0)
    neck = shape == 2
    normal[neck, :2] = rel[neck, :2]
    normal[shape == 3] = rel[shape == 3]
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    part = np.where(shape == 3, HEAD, np.where(shape == 2, NECK, np.where(
        (shape == 1) | (point[:, 2] >= LEGS_FRACTION * persons.height[person]), TOP, LEGS)))
    return PersonHits(rows, t, person, part.astype(np.int8), normal)


# ---------------------------------------------------------------------------------------------------- truth


def head_samples(centres: np.ndarray, eye: np.ndarray, count: int = VISIBILITY_SAMPLES) -> np.ndarray:
    """``count`` points per head (P x count x 3) spread over its silhouette disc seen from ``eye`` (first: centre)."""
    view = centres - eye
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    up = np.where(np.abs(view[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    u = np.cross(view, up)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(view, u)
    rings = [(0.0, 1)] + [(0.5, 6), (0.9, count - 7)] if count > 7 else [(0.0, 1), (0.7, count - 1)]
    offsets: list = []
    for radius, k in rings:
        angle = np.arange(k) * 2 * np.pi / k
        offsets += [(radius * np.cos(a), radius * np.sin(a)) for a in angle]
    ring_offsets = np.array(offsets[:count]) * HEAD_RADIUS
    return centres[:, None, :] + ring_offsets[None, :, 0:1] * u[:, None, :] + ring_offsets[None, :, 1:2] * v[:, None, :]


@dataclass(frozen=True)
class HeadsInImage:
    """The heads whose centre projects inside one image."""

    person: np.ndarray  # int
    xy: np.ndarray  # N x 2, COLMAP pixels
    visible: np.ndarray  # bool
    visible_fraction: np.ndarray


@dataclass(frozen=True)
class PersonTruth:
    """Read back from a dataset's ``persons/`` folder (see the module docstring)."""

    heads: dict[tuple[str, int], np.ndarray]  # (rig, frame) -> P x 3 head centres (world, m)
    time_s: dict[tuple[str, int], float]
    offsets: dict[str, float]  # rig -> frame offset
    period_s: float
    images: dict[str, HeadsInImage]  # image name -> its heads


CSV_HEADER = ["image", "x", "y", "person", "visible", "visible_fraction"]


def heads_csv(rows: list[tuple[str, HeadsInImage]]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_HEADER)
    for name, heads in rows:
        for p, (x, y), vis, frac in zip(heads.person, heads.xy, heads.visible, heads.visible_fraction, strict=True):
            writer.writerow([name, f"{x:.4f}", f"{y:.4f}", int(p), int(vis), f"{frac:.3f}"])
    return out.getvalue()


def read_person_truth(root: Path) -> PersonTruth:
    """The person truth of the dataset in ``root`` (``root/persons/``); InputError when it has none."""
    folder = Path(root) / "persons"
    csv_path = folder / "heads.csv"
    if not csv_path.is_file():
        raise InputError(f"{folder} holds no heads.csv: render the dataset with persons (--persons-per-m2)")
    heads, times, offsets, period = {}, {}, {}, 0.0
    for path in sorted(folder.glob("frame*.json")):
        data = json.loads(path.read_text())
        period = float(data["period_s"])
        instants = [np.asarray(i["heads"], dtype=np.float64).reshape(-1, 3) for i in data["instants"]]
        for rig, entry in data["rigs"].items():
            heads[(rig, int(data["frame"]))] = instants[entry["instant"]]
            times[(rig, int(data["frame"]))] = float(entry["time_s"])
            offsets[rig] = float(entry["offset_frames"])
    columns: dict[str, list[list[float]]] = {}
    with csv_path.open(newline="") as f:
        reader = csv.reader(f)
        if next(reader, None) != CSV_HEADER:
            raise InputError(f"{csv_path} does not start with the header {','.join(CSV_HEADER)}")
        for row in reader:
            columns.setdefault(row[0], []).append([float(v) for v in row[1:]])
    images = {}
    for name, values in columns.items():
        a = np.asarray(values, dtype=np.float64).reshape(-1, 5)
        images[name] = HeadsInImage(a[:, 2].astype(np.int64), a[:, :2], a[:, 3] > 0.5, a[:, 4])
    return PersonTruth(heads, times, offsets, period, images)
