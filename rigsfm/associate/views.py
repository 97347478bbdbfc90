"""A frame's narrow views (``View``: an image's pinhole projection and its detections) and their pose sigmas
from the run's bands."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pycolmap
import scipy.optimize

BAND_Z = 1.959964  # the bands are 95 % two-sided half-widths of a normal distance


@dataclass
class View:
    """One narrow image of a frame: its pinhole (undistorted) projection and its detections."""

    name: str
    k: np.ndarray  # 3x3
    r: np.ndarray  # 3x3 cam_from_world rotation
    t: np.ndarray  # 3
    centre: np.ndarray  # 3, world
    width: int
    height: int
    camera: pycolmap.Camera
    xy: np.ndarray  # N x 2 raw COLMAP pixels
    sigma_pose_px: float = 0.0
    centre_sigma_m: float = 0.0  # the camera centre's 1 sigma relative to the network (the run's uncertainty)
    centre_covariance_m2: np.ndarray | None = None  # its 3x3 covariance (world axes), where the run delivers it
    # The crowd's own correction of the run's pose error (a shift of the undistorted pixels, i.e. a small rotation
    # for a narrow camera) and the band sigma before it.
    shift_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    band_sigma_px: float | None = None
    shift_sigma_px: float | None = None  # the shift's own posterior sigma (None: not estimated)
    grey: np.ndarray | None = None  # the image's greys, where readable (the appearance cue)
    descriptor: np.ndarray | None = None  # N x D appearance of its detections (rigsfm.associate.appearance)
    head_px: float | None = None  # the apparent head radius its descriptors were sampled at (None: not described)
    radius_px: np.ndarray | None = None  # N: the detector's apparent head radius of each detection (px), if given

    @classmethod
    def of(cls, image: pycolmap.Image, xy: np.ndarray) -> View:
        pose = image.cam_from_world()
        camera = image.camera
        # a model's images have their cameras
        return cls(image.name, np.asarray(camera.calibration_matrix(), dtype=np.float64),  # type: ignore[union-attr]
                   pose.rotation.matrix(), np.asarray(pose.translation, dtype=np.float64),
                   # a model's images have their cameras
                   np.asarray(image.projection_center(), dtype=np.float64), camera.width, camera.height, camera,  # type: ignore[arg-type,union-attr]
                   np.asarray(xy, dtype=np.float64).reshape(-1, 2))

    def carry(self, before: View) -> None:
        """Take over what the crowd found about this camera in an earlier frame (a static camera's pose error and
        its persons' distances are the same in every frame): its shift, bands and head size."""
        self.shift_px = before.shift_px.copy()
        self.shift_sigma_px, self.sigma_pose_px = before.shift_sigma_px, before.sigma_pose_px
        self.band_sigma_px = before.band_sigma_px
        self.head_px = before.head_px

    @property
    def focal(self) -> float:
        return float(math.sqrt(abs(self.k[0, 0] * self.k[1, 1])))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistorted pinhole pixels (N x 2) and depths of world points (N x 3)."""
        cam = points @ self.r.T + self.t
        z = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            h = cam @ self.k.T
            uv = np.empty((len(h), 2))
            np.divide(h[:, 0], z, out=uv[:, 0])  # column by column: an N x 2 by N x 1 broadcast runs loops of two
            np.divide(h[:, 1], z, out=uv[:, 1])
        return uv, z

    def projected_covariance(self, points: np.ndarray, covariance: np.ndarray,
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The xx, xy and yy entries of world points' covariances (N x 3 x 3) carried into the pinhole pixels: each
        Jacobian row in closed form (a camera's row minus its depth row), no stacked matrix products."""
        cam = points @ self.r.T + self.t
        z = np.where(np.abs(cam[:, 2]) > 1e-9, cam[:, 2], 1e-9)
        a, b = np.empty((len(cam), 3)), np.empty((len(cam), 3))
        for jacobian, row, f in ((a, 0, self.k[0, 0]), (b, 1, self.k[1, 1])):
            scale, ratio = f / z, cam[:, row] / z
            for i in range(3):  # column by column: an N x 1 by 1 x 3 broadcast runs loops of three
                jacobian[:, i] = scale * (self.r[row, i] - ratio * self.r[2, i])
        ca = np.einsum("nij,nj->ni", covariance, a)
        cb = np.einsum("nij,nj->ni", covariance, b)
        return np.einsum("ni,ni->n", a, ca), np.einsum("ni,ni->n", b, ca), np.einsum("ni,ni->n", b, cb)

    def inside(self, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Where undistorted pixels fall inside the image (through the lens model) in front of the camera."""
        ok = z > 0
        if not ok.any():
            return ok
        normalised = (uv[ok] - self.k[:2, 2]) / np.array([self.k[0, 0], self.k[1, 1]])
        raw = np.asarray(self.camera.img_from_cam(np.c_[normalised, np.ones(len(normalised))]), dtype=np.float64)
        inside = np.all(np.isfinite(raw), axis=1) & (raw[:, 0] >= 0) & (raw[:, 0] <= self.width) \
            & (raw[:, 1] >= 0) & (raw[:, 1] <= self.height)
        ok[np.flatnonzero(ok)] = inside
        return ok


def view_pose_sigmas(names: list[str], bands: dict[tuple[str, str], float]) -> dict[str, float]:
    """Per view, the pose sigma (px, per coordinate) whose pairwise sums explain the pairs' 95 % bands."""
    index = {name: i for i, name in enumerate(names)}
    rows, target = [], []
    for (a, b), band in bands.items():
        if a in index and b in index and band is not None and math.isfinite(band):
            row = np.zeros(len(names))
            row[index[a]] = row[index[b]] = 1.0
            rows.append(row)
            target.append((band / BAND_Z) ** 2)
    if not rows:
        return dict.fromkeys(names, 0.0)
    matrix, target = np.asarray(rows), np.asarray(target)  # type: ignore[assignment]  # the list, as an array
    variance, _ = scipy.optimize.nnls(matrix, target)
    seen = matrix.sum(axis=0) > 0
    fallback = float(np.median(target) / 2.0)
    return {name: float(math.sqrt(variance[i] if seen[i] else fallback)) for name, i in index.items()}
