"""The synthetic arena: geometry (ground, wall, pillars, boxes, a 2 m bar) and ray casting; its options are
``options.SceneOptions``.

World frame: metres, z up, origin on the ground at the arena centre. The ground is the plane z = 0
up to a cylindrical wall (the stands) of radius ``wall_radius``; inside ``centre_radius`` the ground
is a homogeneous grey disc (what the narrow cameras see), outside it a richly textured ring.
Pillars (vertical cylinders) and boxes stand on the ring behind the rigs; with ``persons_per_m2`` a crowd of 3D
persons (rigsfm.synth.persons) stands on the disc, placed into an arena for one instant with ``Arena.with_persons``.

Textures take ~6-9 s per seed to generate; each process keeps its last few (``lru_cache``), and with
``RIGSFM_TEXTURE_CACHE=DIR`` in the environment they are also kept in DIR for other processes (the test suite's
workers share one; a later process reads the same arrays back, so its scenes are identical). DIR is keyed by the
generator's parameters only: empty it when the texture code changes.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from rigsfm.core.io import read_npz, write_npz_atomic
from rigsfm.synth.options import SceneOptions
from rigsfm.synth.persons import Persons, intersect
from rigsfm.synth.textures import Texture, build_pyramid, crowd_texture, procedural_texture

logger = logging.getLogger(__name__)

SKY, GROUND, WALL, OBJECT, PERSON = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class Pillar:
    x: float
    y: float
    radius: float
    height: float
    tex_offset: tuple[float, float]


@dataclass(frozen=True)
class Box:
    x: float
    y: float
    half_size: tuple[float, float, float]  # along the box's local x, y and z (m)
    yaw: float  # radians
    tex_offset: tuple[float, float]


@dataclass(frozen=True)
class Bar:
    """A dark bar lying on the ground between end points ``a`` and ``b`` (bright discs, dark rings)."""

    a: np.ndarray
    b: np.ndarray
    width: float = 0.08
    marker_radius: float = 0.2
    ring_radius: float = 0.4

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.b - self.a))


@dataclass(frozen=True)
class Textures:
    wall: Texture
    ground: Texture
    objects: Texture
    centre: Texture | None
    centre_phase: tuple[float, ...]


@dataclass(frozen=True)
class Arena:
    options: SceneOptions
    pillars: tuple[Pillar, ...]
    boxes: tuple[Box, ...]
    textures: Textures
    bar: Bar | None = None
    persons: Persons | None = None  # the crowd at the instant rendered

    def with_bar(self, bar: Bar | None) -> Arena:
        return replace(self, bar=bar)

    def with_persons(self, persons: Persons | None) -> Arena:
        return replace(self, persons=persons)


@dataclass
class Hits:
    """Per ray: distance ``t`` (inf for sky), surface kind, texture coords (m), unit normal. For a PERSON hit,
    ``object_index`` is the person, ``u`` the part (rigsfm.synth.persons.LEGS ... HEAD) and ``v`` the height (m)."""

    t: np.ndarray
    kind: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    object_index: np.ndarray


OBJECT_BAND = 12.0  # metres of the object texture's width that belong to each pillar or box


TEXTURE_CACHE_ENV = "RIGSFM_TEXTURE_CACHE"


def _shared_arrays(key: str, make: Callable[[], tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """``make()``, or the arrays an earlier call with ``key`` left in ``$RIGSFM_TEXTURE_CACHE`` (when set)."""
    folder = os.environ.get(TEXTURE_CACHE_ENV)
    if not folder:
        return make()
    path = Path(folder) / f"{key}.npz"
    stored = read_npz(path)  # None: not made yet (or unreadable): make it here
    if stored is not None and set(stored) == {f"a{i}" for i in range(len(stored))}:
        return tuple(stored[f"a{i}"] for i in range(len(stored)))
    arrays = make()
    write_npz_atomic(path, {f"a{i}": array for i, array in enumerate(arrays)})
    return arrays


@lru_cache(maxsize=4)
def _surround_textures(
    seed: int, wall_radius: float, wall_height: float, num_objects: int
) -> tuple[Texture, Texture, Texture]:
    side = 2 * wall_radius + 1.0

    def make() -> tuple[np.ndarray, ...]:
        rng = np.random.default_rng([seed, 7])
        circumference = 2 * np.pi * wall_radius
        wall = procedural_texture(rng, circumference, wall_height, 0.025, wrap=True)
        ground = procedural_texture(rng, side, side, 0.02, density=1.0, min_size=0.1, max_size=2.5)
        # One band per object: no two pillars or boxes show the same patch (which gave SIFT false matches).
        width = OBJECT_BAND * max(num_objects, 1)
        objects = procedural_texture(rng, width, 12.0, 0.015, density=2.5, min_size=0.08, max_size=1.2, wrap=True)
        logger.debug("generated wall, ground and object textures for seed %d", seed)
        return wall, ground, objects

    wall, ground, objects = _shared_arrays(f"surround_{seed}_{wall_radius!r}_{wall_height!r}_{num_objects}", make)
    return (
        Texture(build_pyramid(wall), 0.025, (0.0, 0.0), wrap=True),
        Texture(build_pyramid(ground), 0.02, (-side / 2, -side / 2)),
        Texture(build_pyramid(objects), 0.015, (0.0, 0.0), wrap=True),
    )


@lru_cache(maxsize=2)
def _crowd_texture(seed: int, centre_radius: float) -> Texture:
    size = 2 * centre_radius + 2.0
    (crowd,) = _shared_arrays(f"crowd_{seed}_{centre_radius!r}",
                              lambda: (crowd_texture(np.random.default_rng([seed, 8]), size, 0.01),))
    return Texture(build_pyramid(crowd), 0.01, (-size / 2, -size / 2))


def make_textures(options: SceneOptions) -> Textures:
    """All textures of an arena, generated from ``options.seed`` (cached: same seed, same arena)."""
    wall, ground, objects = _surround_textures(
        options.seed, options.wall_radius, options.wall_height, options.num_pillars + options.num_boxes
    )
    centre = _crowd_texture(options.seed, options.centre_radius) if options.textured_centre else None
    phase = tuple(float(p) for p in np.random.default_rng([options.seed, 9]).uniform(0, 2 * np.pi, 4))
    return Textures(wall=wall, ground=ground, objects=objects, centre=centre, centre_phase=phase)


def _band_offset(index: int, draw: np.ndarray) -> tuple[float, float]:
    """Texture offset of object ``index``: inside its own band, a little jitter from ``draw`` (0..12)."""
    return float(OBJECT_BAND * index + draw[0] / 12.0), float(draw[1] / 12.0)


def build_arena(options: SceneOptions) -> Arena:
    """Pillars and boxes on the ring behind the rig circle, plus the textures (no bar yet)."""
    rng = np.random.default_rng([options.seed, 11])
    r_min, r_max = options.radius + 3.0, options.wall_radius - 2.5
    placed: list[tuple[float, float, float]] = []

    def free_spot(clearance: float) -> tuple[float, float]:
        for _ in range(200):
            r, phi = rng.uniform(r_min, r_max), rng.uniform(0, 2 * np.pi)
            x, y = r * np.cos(phi), r * np.sin(phi)
            if all(np.hypot(x - px, y - py) > clearance + pc + 0.5 for px, py, pc in placed):
                placed.append((x, y, clearance))
                return float(x), float(y)
        raise RuntimeError("could not place scene objects; reduce num_pillars/num_boxes")

    pillars: list[Pillar] = []
    for _ in range(options.num_pillars):
        radius = float(rng.uniform(0.4, 0.8))
        x, y = free_spot(radius)
        height = float(rng.uniform(5.0, 10.0))
        pillars.append(Pillar(x, y, radius, height, _band_offset(len(pillars), rng.uniform(0, 12, 2))))
    boxes: list = []
    for _ in range(options.num_boxes):
        half = (float(rng.uniform(0.5, 1.2)), float(rng.uniform(0.5, 1.2)), float(rng.uniform(0.4, 1.2)))
        x, y = free_spot(float(np.hypot(half[0], half[1])))
        yaw = float(rng.uniform(0, np.pi))
        boxes.append(Box(x, y, half, yaw, _band_offset(options.num_pillars + len(boxes), rng.uniform(0, 12, 2))))
    return Arena(options, tuple(pillars), tuple(boxes), make_textures(options))


def _closer(hits: Hits, t: np.ndarray, kind: int, index: int = -1, rows: np.ndarray | None = None) -> None:
    """Keep the new hit distances ``t`` (of all rays, or of ``rows``) that beat the current ones."""
    rows = np.arange(len(hits.t)) if rows is None else rows
    better = np.isfinite(t) & (t > 1e-9) & (t < hits.t[rows])
    rows = rows[better]
    hits.t[rows] = t[better]
    hits.kind[rows] = kind
    hits.object_index[rows] = index


SECTORS = 4096  # azimuth sectors of the rays' first cull (_rays_towards)


def _sectors(azimuth: np.ndarray) -> np.ndarray:
    """Each ray's azimuth sector, 0..SECTORS-1 over [-pi, pi] (0 for a NaN ray: the exact test leaves it out)."""
    sector = np.minimum((azimuth + np.pi) * (SECTORS / (2 * np.pi)), SECTORS - 1)
    return np.where(np.isfinite(sector), sector, 0.0).astype(np.int16)


def _rays_towards(o: np.ndarray, azimuth: np.ndarray, sectors: np.ndarray, x: float, y: float,
                  reach: float) -> np.ndarray:
    """Indices (ascending) of rays whose horizontal direction passes within ``reach`` of (x, y) (a cheap cull).
    The rays of the sectors around that direction (0.01 rad wider) are tested, not all: 3.6 instead of 39 ms for
    2 M rays, the same indices."""
    dist = float(np.hypot(x - o[0], y - o[1]))
    if dist <= reach + 1e-6:
        return np.arange(len(azimuth))
    half = np.arcsin(reach / dist) + 1e-3
    centre = np.arctan2(y - o[1], x - o[0])
    low, high = (int(np.floor((centre + side * (half + 1e-2) + np.pi) * (SECTORS / (2 * np.pi)))) for side in (-1, 1))
    if low < 0:
        candidates = np.flatnonzero((sectors >= low + SECTORS) | (sectors <= high))
    elif high >= SECTORS:
        candidates = np.flatnonzero((sectors >= low) | (sectors <= high - SECTORS))
    else:
        candidates = np.flatnonzero((sectors >= low) & (sectors <= high))
    delta = np.abs(np.mod(azimuth[candidates] - centre + np.pi, 2 * np.pi) - np.pi)
    return candidates[delta <= half]


def trace(arena: Arena, origin: np.ndarray, dirs: np.ndarray) -> Hits:
    """Intersect rays ``origin + t * dirs`` (dirs: Nx3 unit vectors) with the arena."""
    opt = arena.options
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    n = len(d)
    hits = Hits(
        np.full(n, np.inf),
        np.full(n, SKY, np.int8),
        np.zeros(n),
        np.zeros(n),
        np.zeros((n, 3)),
        np.full(n, -1, np.int32),
    )
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    a = dx * dx + dy * dy
    safe_a = np.where(a > 1e-15, a, 1e-15)
    azimuth = np.arctan2(dy, dx)
    sectors = _sectors(azimuth)
    with np.errstate(invalid="ignore", divide="ignore"):
        # Wall: inside a cylinder, the far root; valid between the ground and the wall top.
        b = 2 * (o[0] * dx + o[1] * dy)
        c = o[0] ** 2 + o[1] ** 2 - opt.wall_radius**2
        t = (-b + np.sqrt(b * b - 4 * safe_a * c)) / (2 * safe_a)
        z = o[2] + t * dz
        t = np.where((z >= 0) & (z <= opt.wall_height) & (a > 1e-15), t, np.inf)
        _closer(hits, t, WALL)
        # Ground plane z = 0 (inside the wall).
        t = np.where(dz < 0, -o[2] / dz, np.inf)
        _closer(hits, t, GROUND)
        for i, p in enumerate(arena.pillars):
            rows = _rays_towards(o, azimuth, sectors, p.x, p.y, p.radius)
            ox, oy = o[0] - p.x, o[1] - p.y
            b = 2 * (ox * dx[rows] + oy * dy[rows])
            c = ox * ox + oy * oy - p.radius**2
            t = (-b - np.sqrt(b * b - 4 * safe_a[rows] * c)) / (2 * safe_a[rows])
            z = o[2] + t * dz[rows]
            t = np.where((z >= 0) & (z <= p.height), t, np.inf)
            _closer(hits, t, OBJECT, i, rows)
        for j, box in enumerate(arena.boxes):
            rows = _rays_towards(o, azimuth, sectors, box.x, box.y, float(np.hypot(*box.half_size[:2])))
            cos_y, sin_y = np.cos(box.yaw), np.sin(box.yaw)
            lo = np.array([o[0] - box.x, o[1] - box.y, o[2] - box.half_size[2]])
            local_o = np.array([cos_y * lo[0] + sin_y * lo[1], -sin_y * lo[0] + cos_y * lo[1], lo[2]])
            sub_x, sub_y = dx[rows], dy[rows]
            local_d = np.stack(
                [cos_y * sub_x + sin_y * sub_y, -sin_y * sub_x + cos_y * sub_y, dz[rows]], axis=1
            )
            local_d = np.where(np.abs(local_d) < 1e-12, 1e-12, local_d)
            half = np.array(box.half_size)
            t1, t2 = (-half - local_o) / local_d, (half - local_o) / local_d
            t_near = np.minimum(t1, t2).max(axis=1)
            t_far = np.maximum(t1, t2).min(axis=1)
            t = np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)
            _closer(hits, t, OBJECT, len(arena.pillars) + j, rows)
    _surface_coordinates(arena, o, d, hits)
    if arena.persons is not None and len(arena.persons):
        found = intersect(arena.persons, o, d, hits.t)
        better = found.t < hits.t[found.rows]
        rows = found.rows[better]
        hits.t[rows] = found.t[better]
        hits.kind[rows] = PERSON
        hits.object_index[rows] = found.person[better]
        hits.u[rows] = found.part[better]
        hits.v[rows] = o[2] + found.t[better] * d[rows, 2]
        hits.normal[rows] = found.normal[better]
    return hits


def _surface_coordinates(arena: Arena, o: np.ndarray, d: np.ndarray, hits: Hits) -> None:
    """Fill texture coordinates (metres) and normals of every hit."""
    opt = arena.options
    finite = np.isfinite(hits.t)
    p = o + np.where(finite, hits.t, 0.0)[:, None] * d
    ground = hits.kind == GROUND
    hits.u[ground], hits.v[ground] = p[ground, 0], p[ground, 1]
    hits.normal[ground] = (0.0, 0.0, 1.0)
    wall = hits.kind == WALL
    theta = np.mod(np.arctan2(p[wall, 1], p[wall, 0]), 2 * np.pi)
    # u grows to the right for a viewer inside the arena, v downwards: text on the wall reads normally.
    hits.u[wall], hits.v[wall] = (2 * np.pi - theta) * opt.wall_radius, opt.wall_height - p[wall, 2]
    hits.normal[wall] = np.stack([-np.cos(theta), -np.sin(theta), np.zeros_like(theta)], axis=1)
    objects = np.flatnonzero(hits.kind == OBJECT)  # each object's rays picked among these, not among all rays
    owner = hits.object_index[objects]
    for i, pillar in enumerate(arena.pillars):
        sel = objects[owner == i]
        phi = np.mod(np.arctan2(p[sel, 1] - pillar.y, p[sel, 0] - pillar.x), 2 * np.pi)
        hits.u[sel] = phi * pillar.radius + pillar.tex_offset[0]
        hits.v[sel] = pillar.height - p[sel, 2] + pillar.tex_offset[1]
        hits.normal[sel] = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    for j, box in enumerate(arena.boxes):
        sel = objects[owner == len(arena.pillars) + j]
        cos_y, sin_y = np.cos(box.yaw), np.sin(box.yaw)
        rel = p[sel] - np.array([box.x, box.y, box.half_size[2]])
        local = np.stack(
            [cos_y * rel[:, 0] + sin_y * rel[:, 1], -sin_y * rel[:, 0] + cos_y * rel[:, 1], rel[:, 2]], axis=1
        )
        axis = np.argmax(np.abs(local) / np.array(box.half_size), axis=1)
        sign = np.sign(local[np.arange(len(local)), axis])
        normal_local = np.zeros_like(local)
        normal_local[np.arange(len(local)), axis] = sign
        hits.normal[sel] = np.stack(
            [
                cos_y * normal_local[:, 0] - sin_y * normal_local[:, 1],
                sin_y * normal_local[:, 0] + cos_y * normal_local[:, 1],
                normal_local[:, 2],
            ],
            axis=1,
        )
        uu = np.where(axis == 0, local[:, 1], local[:, 0]) + 3.0 * axis + 1.5 * (sign > 0)
        vv = np.where(axis == 2, local[:, 1], -local[:, 2])
        hits.u[sel], hits.v[sel] = uu + box.tex_offset[0], vv + box.tex_offset[1]
