"""Ray casting one camera image of the arena (numpy + cv2.remap), and exact projection helpers.

Per-pixel rays come from pycolmap's own ``Camera.cam_ray_from_img`` at the pixel centres
(x + 0.5, y + 0.5) -- COLMAP's pixel convention -- so the rendered images follow the given OPENCV
model (including its distortion) exactly as COLMAP interprets it.
"""

from __future__ import annotations

import functools
import logging
import time

import numpy as np
import pycolmap

from rigsfm.core.geometry import project_world
from rigsfm.synth.scene import GROUND, OBJECT, PERSON, SKY, WALL, Arena, Bar, Hits, trace

logger = logging.getLogger(__name__)

LIGHT = np.array([0.4, 0.3, 0.85]) / np.linalg.norm([0.4, 0.3, 0.85])
CENTRE_GREY = 0.5
CENTRE_BLEND = 0.6  # metres over which the homogeneous disc fades into the textured ring
BAR_GREY, MARKER_GREY, RING_GREY = 0.1, 0.95, 0.08


def pixel_rays(camera: pycolmap.Camera) -> np.ndarray:
    """Unit bearing vectors (H*W x 3, row-major, read-only) in the camera frame through every pixel centre.
    Cached for the last few cameras: a recording renders each camera in many frames, and ``cam_ray_from_img``
    takes ~2 s for a 1624x1234 camera."""
    return _pixel_rays(camera.model.name, camera.width, camera.height, tuple(float(p) for p in camera.params))


@functools.lru_cache(maxsize=4)
def _pixel_rays(model: str, width: int, height: int, params: tuple[float, ...]) -> np.ndarray:
    camera = pycolmap.Camera(model=model, width=width, height=height, params=list(params))
    x, y = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    xy = np.column_stack([x.ravel(), y.ravel()]).astype(np.float64)
    rays = np.asarray(camera.cam_ray_from_img(xy), dtype=np.float64)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays.flags.writeable = False
    return rays


def camera_centre(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    return np.asarray(cam_from_world.inverse().translation, dtype=np.float64)


def visible(
    arena: Arena,
    camera: pycolmap.Camera,
    cam_from_world: pycolmap.Rigid3d,
    points: np.ndarray,
    margin: float = 0.0,
) -> np.ndarray:
    """Whether world points project inside the image (``margin`` px from the border) unoccluded.

    Points far outside the field of view that the distortion polynomial folds back into the image are
    not visible (``rigsfm.core.geometry.project``).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    _, inside = project_world(camera, cam_from_world, points, margin_px=margin)
    centre = camera_centre(cam_from_world)
    offsets = points - centre
    dist = np.linalg.norm(offsets, axis=1)
    hits = trace(arena, centre, offsets / dist[:, None])
    return inside & (hits.t >= dist - 1e-6 * np.maximum(dist, 1.0) - 1e-6)


def _coverage(distance: np.ndarray, radius: float, footprint: np.ndarray) -> np.ndarray:
    """Anti-aliased inside-ness of a shape edge: 1 inside, 0 outside, a ramp one footprint wide."""
    return np.clip((radius - distance) / np.maximum(footprint, 1e-6) + 0.5, 0.0, 1.0)


def _paint_bar(bar: Bar, xy: np.ndarray, footprint: np.ndarray, values: np.ndarray) -> np.ndarray:
    a, b = bar.a[:2], bar.b[:2]
    axis = (b - a) / np.linalg.norm(b - a)
    rel = xy - a
    along = rel @ axis
    across = np.abs(rel @ np.array([-axis[1], axis[0]]))
    beyond = np.maximum(np.maximum(-along, along - bar.length), 0.0)
    body = _coverage(np.hypot(across, beyond), bar.width / 2, footprint)
    values = values + body * (BAR_GREY - values)
    for end in (a, b):
        distance = np.linalg.norm(xy - end, axis=1)
        values = values + _coverage(distance, bar.ring_radius, footprint) * (RING_GREY - values)
        values = values + _coverage(distance, bar.marker_radius, footprint) * (MARKER_GREY - values)
    return values


def _centre_values(arena: Arena, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    textures = arena.textures
    if textures.centre is not None:
        return textures.centre.sample(x, y, footprint)
    p = textures.centre_phase
    # Very low-amplitude, smooth shading only: a few grey levels over metres, no features.
    return (
        CENTRE_GREY
        + 0.010 * np.sin(0.21 * x + 0.13 * y + p[0])
        + 0.008 * np.sin(-0.17 * x + 0.23 * y + p[1])
        + 0.006 * np.sin(0.05 * x - 0.07 * y + p[2])
    )


def shade(arena: Arena, origin: np.ndarray, dirs: np.ndarray, hits: Hits, pixel_angle: float) -> np.ndarray:
    """Grey value in [0, 1] of every ray, sampling textures at the pixel's footprint (mip-mapping)."""
    opt = arena.options
    textures = arena.textures
    values = np.zeros(len(dirs))
    cos_incidence = np.abs(np.einsum("ij,ij->i", hits.normal, dirs))
    t = np.where(np.isfinite(hits.t), hits.t, 0.0)
    footprint = t * pixel_angle / np.sqrt(np.maximum(cos_incidence, 0.02))
    light = 0.62 + 0.38 * np.clip(hits.normal @ LIGHT, 0.0, 1.0)

    sky = hits.kind == SKY
    values[sky] = 0.80 + 0.12 * dirs[sky, 2]
    wall = hits.kind == WALL
    values[wall] = textures.wall.sample(hits.u[wall], hits.v[wall], footprint[wall])
    obj = hits.kind == OBJECT
    values[obj] = textures.objects.sample(hits.u[obj], hits.v[obj], footprint[obj])

    ground = np.flatnonzero(hits.kind == GROUND)
    gx, gy, fp = hits.u[ground], hits.v[ground], footprint[ground]
    ring_weight = np.clip((np.hypot(gx, gy) - opt.centre_radius) / CENTRE_BLEND, 0.0, 1.0)
    ground_values = np.zeros(len(ground))
    use = ring_weight > 0
    ground_values[use] = ring_weight[use] * textures.ground.sample(gx[use], gy[use], fp[use])
    use = ring_weight < 1
    ground_values[use] += (1 - ring_weight[use]) * _centre_values(arena, gx[use], gy[use], fp[use])
    if arena.bar is not None:
        near = np.hypot(
            gx - (arena.bar.a[0] + arena.bar.b[0]) / 2, gy - (arena.bar.a[1] + arena.bar.b[1]) / 2
        )
        sel = near < arena.bar.length / 2 + arena.bar.ring_radius + 0.5
        ground_values[sel] = _paint_bar(
            arena.bar, np.column_stack([gx[sel], gy[sel]]), fp[sel], ground_values[sel]
        )
    values[ground] = ground_values
    person = np.flatnonzero(hits.kind == PERSON)
    if len(person):
        values[person] = arena.persons.greys[  # type: ignore[union-attr]  # person hits: persons are there
            hits.object_index[person], hits.u[person].astype(np.int64)]
    values[~sky] *= light[~sky]
    return values


def render_clean(arena: Arena, camera: pycolmap.Camera, cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """Noise-free float image (H x W, values in [0, 1]) seen by ``camera`` at ``cam_from_world``."""
    start = time.perf_counter()
    rays_cam = pixel_rays(camera)
    world_from_cam = cam_from_world.inverse().matrix()
    dirs = rays_cam @ world_from_cam[:, :3].T
    origin = world_from_cam[:, 3]
    hits = trace(arena, origin, dirs)
    pixel_angle = 1.0 / float(np.mean([camera.focal_length_x, camera.focal_length_y]))
    image = shade(arena, origin, dirs, hits, pixel_angle).reshape(camera.height, camera.width)
    vignetting = arena.options.vignetting
    if vignetting > 0:
        x, y = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
        cx, cy = camera.principal_point_x, camera.principal_point_y
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / ((camera.width / 2) ** 2 + (camera.height / 2) ** 2)
        image *= 1.0 - vignetting * r2
    logger.debug("rendered %dx%d in %.2f s", camera.width, camera.height, time.perf_counter() - start)
    return image


def to_uint8(image: np.ndarray, rng: np.random.Generator | None, noise_sigma: float) -> np.ndarray:
    """8-bit grey image with Gaussian noise of ``noise_sigma`` grey levels (none if rng is None)."""
    # Pixels whose ray the distortion model cannot invert (strong wide-angle corners) come out NaN: black.
    grey = np.nan_to_num(image, nan=0.0) * 255.0
    if rng is not None and noise_sigma > 0:
        grey = grey + rng.normal(0.0, noise_sigma, grey.shape)
    return np.clip(np.rint(grey), 0, 255).astype(np.uint8)


def render_image(
    arena: Arena,
    camera: pycolmap.Camera,
    cam_from_world: pycolmap.Rigid3d,
    rng: np.random.Generator | None = None,
    noise_sigma: float | None = None,
) -> np.ndarray:
    """Rendered 8-bit grey image; noise of ``noise_sigma`` (default: the scene's) if ``rng`` is given."""
    sigma = arena.options.noise_sigma if noise_sigma is None else noise_sigma
    return to_uint8(render_clean(arena, camera, cam_from_world), rng, sigma)
