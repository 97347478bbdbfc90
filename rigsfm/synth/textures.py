"""Procedural, seeded textures (nothing is downloaded) and their mip-mapped bilinear sampling.

Every texture is a float32 image in [0, 1] with a metric texel size. The generator mixes
band-limited 1/f noise (periodic, so a texture wrapped round the arena wall has no seam), blobs,
rectangles, strokes and letter strings of many sizes and contrasts: rich, non-periodic structure on
which SIFT finds plenty of distinctive keypoints.
"""

from __future__ import annotations

import logging
import string
from dataclasses import dataclass

import cv2
import numpy as np

logger = logging.getLogger(__name__)

MAX_LEVELS = 7
FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)
LETTERS = string.ascii_uppercase + string.digits


@dataclass(frozen=True)
class Texture:
    """A mip pyramid (level 0 first) mapping metric surface coordinates (u, v) to grey values.

    Texel (i, j) of level 0 has its centre at ``(u, v) = origin + texel * (j, i)``.
    """

    levels: tuple[np.ndarray, ...]
    texel: float
    origin: tuple[float, float] = (0.0, 0.0)
    wrap: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return self.levels[0].shape

    def sample(self, u: np.ndarray, v: np.ndarray, footprint: np.ndarray | float) -> np.ndarray:
        """Bilinear, trilinearly mip-mapped values at metric (u, v); ``footprint`` = metres per pixel."""
        u = np.asarray(u, dtype=np.float64).ravel()
        v = np.asarray(v, dtype=np.float64).ravel()
        tu = (u - self.origin[0]) / self.texel
        tv = (v - self.origin[1]) / self.texel
        if self.wrap:
            tu = np.mod(tu, self.shape[1])
        level = np.log2(np.maximum(np.broadcast_to(footprint, u.shape) / self.texel, 1.0))
        level = np.minimum(level, len(self.levels) - 1)
        out = np.zeros(u.shape, dtype=np.float64)
        border = cv2.BORDER_WRAP if self.wrap else cv2.BORDER_REFLECT
        for k, image in enumerate(self.levels):
            weight = np.clip(1.0 - np.abs(level - k), 0.0, 1.0)
            use = weight > 0
            if not np.any(use):
                continue
            scale = 2.0**-k
            mu = (tu[use] + 0.5) * scale - 0.5
            mv = (tv[use] + 0.5) * scale - 0.5
            out[use] += weight[use] * remap_points(image, mu, mv, border)
        return out


def remap_points(image: np.ndarray, x: np.ndarray, y: np.ndarray, border: int) -> np.ndarray:
    """Bilinear values of ``image`` at float pixel coordinates (OpenCV convention) via cv2.remap."""
    n = x.size
    cols = 1024
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, dtype=np.float32)
    my = np.zeros(rows * cols, dtype=np.float32)
    mx[:n], my[:n] = x, y
    values = cv2.remap(
        image, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR, borderMode=border
    )
    return values.reshape(-1)[:n].astype(np.float64)


def build_pyramid(image: np.ndarray) -> tuple[np.ndarray, ...]:
    """Level 0 lightly pre-blurred (anti-aliasing), then cv2.pyrDown until small."""
    levels = [cv2.GaussianBlur(image.astype(np.float32), (0, 0), 0.5)]
    while len(levels) < MAX_LEVELS and min(levels[-1].shape) >= 32:
        levels.append(cv2.pyrDown(levels[-1]))
    return tuple(levels)


def fractal_noise(
    rng: np.random.Generator, shape: tuple[int, int], texel: float, longest: float, shortest: float
) -> np.ndarray:
    """Periodic 1/f noise (zero mean, unit std) with wavelengths between ``shortest`` and ``longest`` m."""
    h, w = shape
    white = rng.standard_normal((h, w)).astype(np.float32)
    spectrum = np.fft.rfft2(white)
    fy = np.fft.fftfreq(h, d=texel)[:, None]
    fx = np.fft.rfftfreq(w, d=texel)[None, :]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = 1.0
    gain = f**-1.0 * (f >= 1.0 / longest) * np.exp(-((f * shortest) ** 2))
    gain[0, 0] = 0.0
    noise = np.fft.irfft2(spectrum * gain, s=(h, w)).astype(np.float32)
    return (noise - noise.mean()) / max(float(noise.std()), 1e-9)


def _random_grey(rng: np.random.Generator) -> int:
    return int(rng.choice([rng.integers(0, 70), rng.integers(60, 200), rng.integers(185, 256)]))


def draw_elements(
    rng: np.random.Generator,
    canvas: np.ndarray,
    texel: float,
    *,
    density: float,
    min_size: float,
    max_size: float,
    margin_x: int = 0,
) -> None:
    """Draw random rectangles, ellipses, strokes, polygons and letter strings (sizes in metres)."""
    h, w = canvas.shape
    area = h * w * texel * texel
    count = int(density * area)
    log_min, log_max = np.log(min_size), np.log(max_size)
    x_lo, x_hi = margin_x, max(margin_x + 1, w - margin_x)
    for _ in range(count):
        size = float(np.exp(rng.uniform(log_min, log_max))) / texel
        x, y = int(rng.integers(x_lo, x_hi)), int(rng.integers(0, h))
        grey = _random_grey(rng)
        kind = rng.random()
        if kind < 0.28:
            dx, dy = size * rng.uniform(0.3, 1.0), size * rng.uniform(0.3, 1.0)
            thickness = -1 if rng.random() < 0.7 else max(1, int(size * 0.08))
            p1, p2 = (int(x - dx / 2), int(y - dy / 2)), (int(x + dx / 2), int(y + dy / 2))
            cv2.rectangle(canvas, p1, p2, grey, thickness, cv2.LINE_AA)
        elif kind < 0.55:
            axes = (max(1, int(size * rng.uniform(0.15, 0.5))), max(1, int(size * rng.uniform(0.15, 0.5))))
            thickness = -1 if rng.random() < 0.75 else max(1, int(size * 0.06))
            angle = float(rng.uniform(0, 180))
            cv2.ellipse(canvas, (x, y), axes, angle, 0, 360, grey, thickness, cv2.LINE_AA)
        elif kind < 0.67:
            pts = np.array([x, y]) + rng.normal(0, size * 0.4, (int(rng.integers(3, 7)), 2))
            cv2.fillPoly(canvas, [pts.astype(np.int32)], grey, cv2.LINE_AA)
        elif kind < 0.77:
            pts = np.array([x, y]) + np.cumsum(
                rng.normal(0, size * 0.3, (int(rng.integers(2, 6)), 2)), axis=0
            )
            thick = max(1, int(size * rng.uniform(0.03, 0.12)))
            cv2.polylines(canvas, [pts.astype(np.int32)], False, grey, thick, cv2.LINE_AA)
        else:
            text = "".join(rng.choice(list(LETTERS), int(rng.integers(1, 6))))
            font = int(rng.choice(FONTS))
            scale = size * 0.6 / 22.0
            thick = max(1, int(scale * rng.uniform(1.0, 3.5)))
            cv2.putText(canvas, text, (x, y), font, scale, grey, thick, cv2.LINE_AA)


def procedural_texture(
    rng: np.random.Generator,
    width_m: float,
    height_m: float,
    texel: float,
    *,
    density: float = 1.2,
    min_size: float = 0.15,
    max_size: float = 3.0,
    wrap: bool = False,
) -> np.ndarray:
    """A rich, non-periodic grey texture of ``width_m x height_m`` metres, float32 in [0, 1]."""
    w, h = int(np.ceil(width_m / texel)), int(np.ceil(height_m / texel))
    base = fractal_noise(rng, (h, w), texel, longest=20.0 * max_size, shortest=2.0 * texel)
    canvas = np.clip(128 + 38 * base, 0, 255).astype(np.uint8)
    margin = int(np.ceil(max_size / texel)) if wrap else 0
    draw_elements(rng, canvas, texel, density=density, min_size=min_size, max_size=max_size, margin_x=margin)
    image = canvas.astype(np.float32) / 255.0
    # Low-frequency contrast and brightness variation, so no two regions look alike.
    contrast = 0.75 + 0.3 * fractal_noise(rng, (h, w), texel, longest=40.0, shortest=4.0)
    brightness = 0.08 * fractal_noise(rng, (h, w), texel, longest=40.0, shortest=6.0)
    mean = float(image.mean())
    image = mean + (image - mean) * np.clip(contrast, 0.3, 1.3) + brightness
    fine = 0.04 * fractal_noise(rng, (h, w), texel, longest=0.5, shortest=texel)
    return np.clip(image + fine, 0.02, 0.98).astype(np.float32)


def crowd_texture(rng: np.random.Generator, size_m: float, texel: float) -> np.ndarray:
    """A dense crowd-like texture (heads, shoulders, clothes) for the optional textured centre."""
    w = h = int(np.ceil(size_m / texel))
    base = fractal_noise(rng, (h, w), texel, longest=4.0, shortest=2.0 * texel)
    canvas = np.clip(110 + 35 * base, 0, 255).astype(np.uint8)
    count = int(3.0 * size_m * size_m)
    for _ in range(count):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        body = (int(rng.uniform(0.18, 0.3) / texel), int(rng.uniform(0.1, 0.18) / texel))
        cv2.ellipse(
            canvas, (x, y), body, float(rng.uniform(0, 180)), 0, 360, _random_grey(rng), -1, cv2.LINE_AA
        )
        head = int(rng.uniform(0.08, 0.12) / texel)
        cv2.circle(canvas, (x, y), head, int(rng.integers(10, 90)), -1, cv2.LINE_AA)
    draw_elements(rng, canvas, texel, density=0.5, min_size=0.05, max_size=0.5)
    return canvas.astype(np.float32) / 255.0
