"""The 95 % epipolar band of every narrow pair, linear in the joint covariance.

:func:`narrow_pair_bands`: the band an analyst can search. A pixel ``x_i`` of narrow image i is clicked, its
epipolar line drawn in j with the *estimated* cameras and pose (pinhole pixels of j, the frame of ``F_ji``),
and the correspondence ``x_j`` sought near it. Under a possible truth (a draw from the joint covariance), the
scene point is on the drawn ray of ``x_i`` at the analysis point's depth, ``x_j`` is its projection with the
drawn camera j, and ``d`` its distance from the estimated line. The draws' effect on ``d`` is linear to far
below a pixel (errors of 0.1 deg and a few pixels), so ``d = J z``: ``J`` (points x parameters) comes from
the chain rule on the poses and from finite differences through pycolmap's camera models (any model, no
camera object per draw), and ``z`` from the covariance. The analysis points are points of the floor (through
scale.yaml's known lengths, else the sparse points' dominant horizontal plane) seen by both narrow cameras on a
15 x 15 grid of image i; without a floor in the shared view, the grid at every depth at which it appears in
image j (0.1x to 100x the pair's distance, uniform in inverse depth). The band half-width is the 95 % quantile
of ``|d|`` pooled over the analysis points and the covariance (exact for the linear model: it solves
``mean_p P(|d_p| <= b) = 0.95``). It is calibrated, not a bound: a true correspondence of a floor point lies
inside it with 95 % probability, pooled over points and over the calibration's possible errors. The
calibration error is one draw per pair, so the share of points inside the band *for one pair* varies from
pair to pair: ``PairBand.predicted_coverage`` is its predicted distribution (one value per draw), and
``predicted_below_85`` the predicted probability that fewer than 85 % of a pair's points lie inside."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pycolmap
from scipy.special import ndtr

from rigsfm.core.geometry import Plane, epipolar_lines, project, skew
from rigsfm.core.names import registered_narrow_images
from rigsfm.run.adjustment.model import sensor_from_rig_view
from rigsfm.run.adjustment.narrow import narrow_tangent_jacobians
from rigsfm.run.adjustment.result import JointCovariance

BAND_PROBABILITY = 0.95
PAIR_COVERAGE_LEVEL = 0.85  # the per-pair coverage whose predicted shortfall is reported


def grid_pixels(camera: pycolmap.Camera, n: int = 15) -> np.ndarray:
    """Centres of an n x n grid of cells over the image (COLMAP pixels)."""
    u = (np.arange(n) + 0.5) / n
    return np.array([(x * camera.width, y * camera.height) for y in u for x in u], dtype=np.float64)


def band_points(reconstruction: pycolmap.Reconstruction, image_i: pycolmap.Image, image_j: pycolmap.Image,
                plane: Plane | None, grid: int = 15, num_depths: int = 48,
                min_points: int = 12) -> tuple[np.ndarray, np.ndarray, str]:
    """Analysis points of a pair (module docstring): pixels of image i (N x 2) and their depths in camera i
    (N), kind ``floor`` or ``depths``; empty when the images share no view."""
    camera_i, camera_j = (reconstruction.cameras[im.camera_id] for im in (image_i, image_j))
    pixels = grid_pixels(camera_i, grid)
    rays = np.column_stack([np.asarray(camera_i.cam_from_img(pixels)), np.ones(len(pixels))])
    cam_i_from_world, cam_j_from_world = image_i.cam_from_world(), image_j.cam_from_world()
    j_from_i = cam_j_from_world * cam_i_from_world.inverse()
    m = j_from_i.matrix()
    if plane is not None:
        world_from_i = cam_i_from_world.inverse()
        origin = np.asarray(world_from_i.translation)
        directions = rays @ world_from_i.rotation.matrix().T
        s = plane.intersect(np.broadcast_to(origin, directions.shape), directions)
        finite = np.isfinite(s)
        depth = s[finite]  # directions = R^T [x, y, 1]: the ray parameter is the depth in camera i
        in_i = rays[finite] * depth[:, None]
        seen = project(camera_j, in_i @ m[:, :3].T + m[:, 3])[1]
        if seen.sum() >= min_points:
            return pixels[finite][seen], depth[seen], "floor"
    distance = float(np.linalg.norm(j_from_i.translation))
    depths = 1.0 / np.linspace(1.0 / (0.1 * distance), 1.0 / (100.0 * distance), num_depths)
    in_i = (rays[:, None, :] * depths[None, :, None]).reshape(-1, 3)
    seen = project(camera_j, in_i @ m[:, :3].T + m[:, 3])[1]
    all_pixels = np.repeat(pixels, num_depths, axis=0)
    all_depths = np.tile(depths, len(pixels))
    return all_pixels[seen], all_depths[seen], "depths"


def _camera_steps(camera: pycolmap.Camera, variances: np.ndarray) -> np.ndarray:
    """Finite-difference step per camera parameter: a tenth of its sigma (0 where it has none)."""
    return 0.1 * np.sqrt(np.clip(variances, 0.0, None))


def _with_params(camera: pycolmap.Camera, params: np.ndarray) -> pycolmap.Camera:
    return pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=params)


def ray_jacobian(camera: pycolmap.Camera, pixels: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N, 2, n_params): derivative of the normalised ray ``cam_from_img(pixel)`` with respect to each camera
    parameter (central differences through pycolmap's model; zero where ``steps`` is 0)."""
    out = np.zeros((len(pixels), 2, len(steps)))
    params = np.asarray(camera.params, dtype=np.float64)
    for k in np.flatnonzero(steps > 0):
        up, down = params.copy(), params.copy()
        up[k] += steps[k]
        down[k] -= steps[k]
        out[:, :, k] = (np.asarray(_with_params(camera, up).cam_from_img(pixels))
                        - np.asarray(_with_params(camera, down).cam_from_img(pixels))) / (2 * steps[k])
    return out


def projection_jacobian(camera: pycolmap.Camera, points: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """(N, 2, n_params): derivative of ``cam_from_img_estimated(img_from_cam_drawn(X))`` (the normalised
    coordinates an analyst recovers from the pixel a drawn camera sees) with respect to each parameter."""
    out = np.zeros((len(points), 2, len(steps)))
    params = np.asarray(camera.params, dtype=np.float64)
    for k in np.flatnonzero(steps > 0):
        values = []
        for sign in (1.0, -1.0):
            shifted = params.copy()
            shifted[k] += sign * steps[k]
            pixels = np.asarray(_with_params(camera, shifted).img_from_cam(points, check_cheirality=False))
            values.append(np.asarray(camera.cam_from_img(pixels)))
        out[:, :, k] = (values[0] - values[1]) / (2 * steps[k])
    return out


@dataclass(frozen=True)
class PairBand:
    band_px: float  # half-width holding the true correspondence with BAND_PROBABILITY, pooled
    points: str  # "floor" or "depths"
    num_points: int
    depth_range_m: tuple[float, float]  # of the analysis points, in camera i
    predicted_coverage: np.ndarray = field(repr=False)  # share of the pair's points inside the band, per draw

    @property
    def predicted_below_85(self) -> float:
        """Predicted probability that fewer than 85 % of this pair's points lie inside its band."""
        return float(np.mean(self.predicted_coverage < PAIR_COVERAGE_LEVEL))


class PairModel:
    """The linear model ``d = J z`` of one pair's analysis points (module docstring)."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, covariance: JointCovariance,
                 image_i: pycolmap.Image, image_j: pycolmap.Image, ray_cache: dict):
        rec = reconstruction
        self.images = (image_i, image_j)
        self.cameras = tuple(rec.cameras[im.camera_id] for im in self.images)
        keys = []
        for image in self.images:
            for key in (("frame", image.frame_id), ("sensor_from_rig", image.camera_id), ("camera", image.camera_id)):
                if key in covariance.offsets and key not in keys:
                    keys.append(key)
        self.keys = keys
        self.columns = {key: slice(start, start + covariance.offsets[key][1])
                        for key, start in zip(keys, np.cumsum([0] + [covariance.offsets[k][1] for k in keys]))}
        self.size = sum(covariance.offsets[k][1] for k in keys)
        self.covariance = covariance.sub(keys)
        self.ray_cache = ray_cache
        self.reconstruction = rec

    def _narrow(self, image: pycolmap.Image):
        rec = self.reconstruction
        frame = rec.frame(image.frame_id)
        sensor = sensor_from_rig_view(rec, frame.rig_id, rec.cameras[image.camera_id].sensor_id)
        return frame, sensor

    def _pose_jacobian(self, image: pycolmap.Image, left: np.ndarray) -> np.ndarray:
        """(6, size): ``left`` (6x6, d relative pose / d narrow pose) times d narrow pose / d parameters."""
        frame, sensor = self._narrow(image)
        d_frame, d_sensor = narrow_tangent_jacobians(frame.rig_from_world, sensor)
        out = np.zeros((6, self.size))
        out[:, self.columns[("frame", image.frame_id)]] += left @ d_frame
        key = ("sensor_from_rig", image.camera_id)
        if key in self.columns:
            out[:, self.columns[key]] += left @ d_sensor
        return out

    def pose_jacobian(self) -> np.ndarray:
        """(6, size): ``[w, dt]`` of ``narrow_j_from_narrow_i`` by the parameters."""
        image_i, image_j = self.images
        pose_i, pose_j = image_i.cam_from_world(), image_j.cam_from_world()
        r_q = (pose_j * pose_i.inverse()).rotation.matrix()
        rt = r_q @ np.asarray(pose_i.translation)
        d_q_d_j = np.eye(6)
        d_q_d_j[3:, :3] = skew(rt)
        d_q_d_i = np.zeros((6, 6))
        d_q_d_i[:3, :3] = -r_q
        d_q_d_i[3:, :3] = -skew(rt) @ r_q
        d_q_d_i[3:, 3:] = -r_q
        return self._pose_jacobian(image_j, d_q_d_j) + self._pose_jacobian(image_i, d_q_d_i)

    def jacobian(self, pixels_i: np.ndarray, depths: np.ndarray) -> np.ndarray:
        """(P, size): derivative of each point's distance from its estimated line (pinhole px of j)."""
        image_i, image_j = self.images
        camera_i, camera_j = self.cameras
        pose_i, pose_j = image_i.cam_from_world(), image_j.cam_from_world()
        j_from_i = pose_j * pose_i.inverse()
        r_q = j_from_i.rotation.matrix()
        d_q = self.pose_jacobian()  # (6, size)

        normalised_i = np.asarray(camera_i.cam_from_img(pixels_i))
        x_i = np.column_stack([normalised_i, np.ones(len(pixels_i))]) * depths[:, None]
        x_j = x_i @ r_q.T + np.asarray(j_from_i.translation)
        z = x_j[:, 2]
        d_n_d_x = np.zeros((len(z), 2, 3))  # normalised coordinates in j by the point in j
        d_n_d_x[:, 0, 0] = d_n_d_x[:, 1, 1] = 1.0 / z
        d_n_d_x[:, :, 2] = -x_j[:, :2] / z[:, None] ** 2
        # the point in j: d x_j = -[R_q x_i]x w_q + dt_q + R_q d x_i
        rotated = x_i @ r_q.T
        d_x_d_q = np.zeros((len(z), 3, 6))
        d_x_d_q[:, :, :3] = -np.array([skew(v) for v in rotated])
        d_x_d_q[:, :, 3:] = np.eye(3)
        jac = np.einsum("pab,pbk,kn->pan", d_n_d_x, d_x_d_q, d_q)  # (P, 2, size)
        variances = np.diag(self.covariance)
        key_i, key_j = ("camera", image_i.camera_id), ("camera", image_j.camera_id)
        if key_i in self.columns:
            cache_key = (image_i.name, pixels_i.tobytes())
            if cache_key not in self.ray_cache:
                self.ray_cache[cache_key] = ray_jacobian(camera_i, pixels_i, _camera_steps(camera_i, variances[self.columns[key_i]]))
            d_ray = self.ray_cache[cache_key]  # (P, 2, n)
            d_x_i = np.concatenate([d_ray, np.zeros((len(z), 1, d_ray.shape[2]))], axis=1) * depths[:, None, None]
            jac[:, :, self.columns[key_i]] += np.einsum("pab,bc,pcn->pan", d_n_d_x, r_q, d_x_i)
        if key_j in self.columns:
            jac[:, :, self.columns[key_j]] += projection_jacobian(camera_j, x_j,
                                                                  _camera_steps(camera_j, variances[self.columns[key_j]]))
        lines = epipolar_lines(camera_i, camera_j, j_from_i, pixels_i)
        k_j = np.asarray(camera_j.calibration_matrix())
        weights = np.column_stack([lines[:, 0] * k_j[0, 0], lines[:, 0] * k_j[0, 1] + lines[:, 1] * k_j[1, 1]])
        weights /= np.linalg.norm(lines[:, :2], axis=1)[:, None]
        return np.einsum("pa,pan->pn", weights, jac)


def _draw_parameters(covariance: JointCovariance, num_samples: int, seed: int) -> np.ndarray:
    """(S, all parameters): draws of the joint covariance (Cholesky root over the parameters that are not held;
    held ones, with zero rows, stay 0)."""
    free = np.flatnonzero(np.diag(covariance.covariance) > 0)
    sub = covariance.covariance[np.ix_(free, free)]
    scaling = np.sqrt(np.diag(sub))
    correlation = sub / np.outer(scaling, scaling)
    try:
        root = np.linalg.cholesky(correlation + 1e-12 * np.eye(len(free))) * scaling[:, None]
    except np.linalg.LinAlgError:  # numerically semi-definite: the eigen-root
        values, vectors = np.linalg.eigh(sub)
        root = vectors * np.sqrt(np.clip(values, 0.0, None))
    draws = np.zeros((num_samples, covariance.covariance.shape[0]))
    draws[:, free] = np.random.default_rng(seed).standard_normal((num_samples, len(free))) @ root.T
    return draws


def pooled_quantile(sigmas: np.ndarray, probability: float = BAND_PROBABILITY) -> float:
    """``b`` with ``mean_p P(|N(0, sigma_p^2)| <= b) = probability`` (bisection)."""
    sigmas = np.asarray(sigmas, dtype=np.float64)
    sigmas = np.where(sigmas > 0, sigmas, 1e-300)
    low, high = 0.0, float(sigmas.max()) * 4.0
    for _ in range(50):  # 2^-50 of the range
        middle = 0.5 * (low + high)
        if np.mean(2.0 * ndtr(middle / sigmas) - 1.0) < probability:
            low = middle
        else:
            high = middle
    return high


def narrow_pair_bands(reconstruction: pycolmap.Reconstruction, covariance: JointCovariance,
                      pairs: Sequence[tuple[str, str]] | None = None, plane: Plane | None = None,
                      num_samples: int = 400, seed: int = 0) -> dict[tuple[str, str], PairBand]:
    """:class:`PairBand` of every pair (default: every pair of registered narrow images) whose images share a
    view, with ``plane`` the floor (None: no floor, points at every depth)."""
    images = {im.name: im for im in registered_narrow_images(reconstruction)}
    if pairs is None:
        names = sorted(images)
        pairs = [(a, b) for k, a in enumerate(names) for b in names[k + 1:]]
    ray_cache: dict = {}
    bands = {}
    draws = None  # one set of draws of every parameter, shared by the pairs (drawn at the first pair)
    for name_i, name_j in pairs:
        image_i, image_j = images.get(name_i), images.get(name_j)
        if image_i is None or image_j is None:
            continue
        pixels, depths, kind = band_points(reconstruction, image_i, image_j, plane)
        if len(pixels) == 0:
            continue
        if draws is None:
            draws = _draw_parameters(covariance, num_samples, seed)
        model = PairModel(reconstruction, covariance, image_i, image_j, ray_cache)
        jac = model.jacobian(pixels, depths)
        sigmas = np.sqrt(np.clip(np.einsum("pk,kl,pl->p", jac, model.covariance, jac), 0.0, None))
        band = pooled_quantile(sigmas)
        distances = draws[:, covariance.index(model.keys)] @ jac.T  # (S, P)
        coverage = np.mean(np.abs(distances) <= band, axis=1)
        bands[(name_i, name_j)] = PairBand(band, kind, len(pixels), (float(depths.min()), float(depths.max())),
                                           coverage)
    return bands
