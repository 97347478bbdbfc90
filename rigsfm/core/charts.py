"""The one chart style: colours, type, ticks and axes for every figure rigsfm draws.

Charts are raster images drawn with OpenCV (no matplotlib): the calibration report's bar charts and
coverage maps, ``rigsfm track``'s per-rig series and report.html's histograms; maps drawn as SVG in
report.html take their colours from :data:`PALETTE` too. Colours are named once here, in RGB, and converted
for OpenCV (BGR) or SVG (hex) by :func:`bgr` and :func:`hex_colour`. The same colours mean the same things
everywhere: wide cameras blue, narrow cameras orange, good / used green, flagged / rejected red.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

PALETTE = {  # RGB, 0-255
    "ink": (30, 30, 30),
    "muted": (140, 140, 140),
    "grid": (228, 228, 228),
    "paper": (255, 255, 255),
    "wide": (31, 119, 180),
    "narrow": (230, 85, 13),
    "good": (60, 160, 60),
    "bad": (210, 45, 45),
    "warn": (255, 140, 0),
    "link": (0, 160, 60),
}
SERIES = ((214, 39, 40), (44, 160, 44), (31, 119, 180), (23, 190, 207), (148, 103, 189), (255, 127, 14),
          (140, 86, 75), (127, 127, 127))  # distinct colours for numbered items (e.g. epipolar lines)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def bgr(name_or_rgb) -> tuple[int, int, int]:
    """OpenCV's BGR tuple of a palette name or an RGB triple."""
    r, g, b = PALETTE[name_or_rgb] if isinstance(name_or_rgb, str) else name_or_rgb
    return int(b), int(g), int(r)


def hex_colour(name_or_rgb) -> str:
    """``#rrggbb`` of a palette name or an RGB triple (for SVG)."""
    r, g, b = PALETTE[name_or_rgb] if isinstance(name_or_rgb, str) else name_or_rgb
    return f"#{int(r):02x}{int(g):02x}{int(b):02x}"


def canvas(width: int, height: int) -> np.ndarray:
    return np.full((height, width, 3), 255, np.uint8)


def text(image: np.ndarray, label: str, origin: tuple[int, int], *, size: float = 0.45, colour="ink",
         bold: bool = False) -> None:
    cv2.putText(image, label, (int(origin[0]), int(origin[1])), FONT, size, bgr(colour), 2 if bold else 1,
                cv2.LINE_AA)


def nice_ticks(top: float, count: int = 4) -> list[float]:
    """About ``count`` round tick values from 0 to at least ``top`` (steps of 1, 2, 2.5 or 5 x 10^k)."""
    top = max(float(top), 1e-12)
    raw = top / count
    magnitude = 10 ** np.floor(np.log10(raw))
    step = min((m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw), default=raw)
    return [i * step for i in range(int(np.ceil(top / step - 1e-9)) + 1)]


class Axes:
    """A plot area in an image: value axis from 0 up, horizontal grid lines with tick labels, a frame."""

    def __init__(self, image: np.ndarray, left: int, top: int, right: int, bottom: int, y_top: float,
                 unit: str = ""):
        self.image, self.left, self.top, self.right, self.bottom = image, left, top, right, bottom
        self.ticks = nice_ticks(y_top)
        self.y_max = self.ticks[-1]
        for tick in self.ticks:
            y = self.y(tick)
            cv2.line(image, (left, y), (right, y), bgr("grid"), 1)
            text(image, f"{tick:g}", (6, y + 4), size=0.4, colour="muted")
        cv2.rectangle(image, (left, top), (right, bottom), bgr("muted"), 1)
        if unit:
            text(image, unit, (6, top - 8), size=0.4, colour="muted")

    def y(self, value: float) -> int:
        return round(self.bottom - (self.bottom - self.top) * float(value) / self.y_max)

    def hline(self, value: float, colour, label: str = "", dashed: bool = True) -> None:
        y = self.y(value)
        step = 12 if dashed else self.right - self.left
        for x in range(self.left, self.right, step):
            cv2.line(self.image, (x, y), (min(x + (6 if dashed else step), self.right), y), bgr(colour), 1,
                     cv2.LINE_AA)
        if label:
            text(self.image, label, (self.right - 8 * len(label) - 6, y - 5), size=0.4, colour=colour)


@dataclass(frozen=True)
class MapFrame:
    """A top view of the world (x right, y up, metres) in an image: the plot area over ``x0..x1`` by ``y0..y1`` at
    ``scale`` pixels per metre, inside margins that hold the axes' labels (:meth:`draw_axes`)."""

    x0: float
    y0: float
    x1: float
    y1: float
    scale: float  # pixels per metre
    left: int = 52
    top: int = 40
    right: int = 24
    bottom: int = 48

    @classmethod
    def fit(cls, bounds: Sequence[float], size: int) -> MapFrame:
        """The frame whose longer side of ``bounds`` spans ``size`` pixels less the margins."""
        x0, y0, x1, y1 = (float(v) for v in bounds)
        return cls(x0, y0, x1, y1, (size - cls.left - cls.right) / max(x1 - x0, y1 - y0, 1e-9))

    @property
    def width(self) -> int:
        return self.left + int(round((self.x1 - self.x0) * self.scale)) + self.right

    @property
    def height(self) -> int:
        return self.top + int(round((self.y1 - self.y0) * self.scale)) + self.bottom

    def px(self, xy) -> np.ndarray:
        """Image pixels (Nx2, x right, y down) of world points (Nx2 or more columns, metres)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
        return np.c_[self.left + (xy[:, 0] - self.x0) * self.scale,
                     self.height - self.bottom - (xy[:, 1] - self.y0) * self.scale]

    def step(self, axis: str = "x") -> float:
        """The ticks' spacing (m) along ``axis``: the smallest round length at least 60 px long on x, where labels
        such as -12.5 stand side by side, 30 px on y, where they stand one above the other."""
        raw = (60.0 if axis == "x" else 30.0) / self.scale
        magnitude = 10 ** np.floor(np.log10(raw))
        return float(next(m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw - 1e-12))

    def ticks(self, axis: str) -> list[float]:
        """The labelled values of ``axis`` ("x" or "y") inside the plot: whole multiples of :meth:`step`."""
        lo, hi = (self.x0, self.x1) if axis == "x" else (self.y0, self.y1)
        step = self.step(axis)
        return [round(k * step, 9) + 0.0 for k in range(int(np.ceil(lo / step - 1e-9)), int(np.floor(hi / step + 1e-9)) + 1)]

    def draw_axes(self, image: np.ndarray) -> None:
        """Ticks labelled in metres under the plot (x) and left of it (y), the axes' names and a scale bar one tick
        step long."""
        bottom, right = self.height - self.bottom, self.width - self.right
        cv2.rectangle(image, (self.left, self.top), (right, bottom), bgr("muted"), 1)
        for x in self.ticks("x"):
            u = int(round(self.px([x, self.y0])[0, 0]))
            cv2.line(image, (u, bottom), (u, bottom + 4), bgr("muted"), 1)
            label = f"{x:g}"
            text(image, label, (u - 4 * len(label), bottom + 17), size=0.4, colour="muted")
        for y in self.ticks("y"):
            v = int(round(self.px([self.x0, y])[0, 1]))
            cv2.line(image, (self.left - 4, v), (self.left, v), bgr("muted"), 1)
            label = f"{y:g}"
            text(image, label, (self.left - 8 - 8 * len(label), v + 4), size=0.4, colour="muted")
        text(image, "x (m)", (right - 40, bottom + 40), size=0.4)
        text(image, "y (m)", (4, self.top - 8), size=0.4)
        step = self.step()
        length = int(round(step * self.scale))
        y = bottom + 36
        cv2.line(image, (self.left, y), (self.left + length, y), bgr("ink"), 2)
        for u in (self.left, self.left + length):
            cv2.line(image, (u, y - 4), (u, y + 4), bgr("ink"), 1)
        text(image, f"{step:g} m", (self.left + length + 6, y + 4), size=0.4)


def bar_chart(title: str, labels: Sequence[str], series: Sequence[Sequence[float | None]],
              colours: Sequence[Sequence], lines: Sequence[tuple[float, object, str]] = (), *, unit: str = "px",
              width: int = 960, height: int = 420) -> np.ndarray:
    """Grouped vertical bars (one group per label, one bar per series; ``colours[s][i]`` a palette name or RGB);
    ``lines`` are ``(value, colour, legend)`` dashed horizontal reference lines."""
    image = canvas(width, height)
    left, top, bottom = 60, 40, height - 110
    values = [v for s in series for v in s if v is not None and np.isfinite(v)] + [v for v, _, _ in lines]
    axes = Axes(image, left, top, width - 20, bottom, max(values + [1e-3]) * 1.1, unit)
    text(image, title, (left, 25), size=0.6)
    group = (axes.right - left) / max(1, len(labels))
    bar = max(1.0, group * 0.8 / max(1, len(series)))
    for i in range(len(labels)):
        x0 = left + i * group + group * 0.1
        for j, values_j in enumerate(series):
            value = values_j[i]
            if value is None or not np.isfinite(value):
                continue
            cv2.rectangle(image, (int(x0 + j * bar), axes.y(value)), (int(x0 + (j + 1) * bar) - 1, axes.y(0)),
                          bgr(colours[j][i]), -1)
    for k, (value, colour, legend) in enumerate(lines):
        axes.hline(value, colour)
        text(image, f"{legend} {value:.2f}", (width - 260, top + 15 + 16 * k), size=0.42, colour=colour)
    strip = canvas(height - bottom - 10, width)  # labels drawn along a transposed strip, then rotated
    for i, label in enumerate(labels):
        text(strip, str(label)[:18], (4, int(left + (i + 0.5) * group) + 4), size=0.38)
    image[bottom + 5:height - 5] = cv2.rotate(strip, cv2.ROTATE_90_COUNTERCLOCKWISE)
    return image


def series_panel(image: np.ndarray, y0: int, height: int, values: Sequence[float | None], flagged: Sequence[bool],
                 threshold: float, label: str, unit: str, marks: Sequence[int] = (), *, left: int = 78,
                 right_margin: int = 20) -> None:
    """One value per frame as a line with dots (red where ``flagged``, grey crosses where None), a dashed
    threshold, and vertical ``marks`` (e.g. detected steps) at frame indices."""
    width = image.shape[1]
    finite = [v for v in values if v is not None]
    axes = Axes(image, left, y0 + 26, width - right_margin, y0 + height - 34, max([threshold * 1.5, *finite]) * 1.08)
    n = len(values)

    def px(i: int) -> int:
        return round(left + (axes.right - left) * (0.5 if n == 1 else i / (n - 1)))

    axes.hline(threshold, "bad", f"threshold {threshold:g} {unit}")
    for index in marks:
        cv2.line(image, (px(index), axes.top), (px(index), axes.bottom), bgr("warn"), 2)
    points = [(px(i), axes.y(v)) for i, v in enumerate(values) if v is not None]
    if len(points) > 1:
        cv2.polylines(image, [np.array(points, np.int32)], False, bgr("wide"), 1, cv2.LINE_AA)
    for i, value in enumerate(values):
        if value is None:
            cv2.drawMarker(image, (px(i), axes.bottom - 6), bgr("muted"), cv2.MARKER_TILTED_CROSS, 8, 1)
        else:
            cv2.circle(image, (px(i), axes.y(value)), 4, bgr("bad" if flagged[i] else "wide"), -1, cv2.LINE_AA)
    text(image, label, (left, y0 + 18), size=0.5)
    for i in sorted({0, n // 2, n - 1}):
        text(image, str(i), (px(i) - 4, axes.bottom + 16), size=0.4, colour="muted")


def histogram(values: np.ndarray, title: str, upper: float, *, bins: int = 24, unit: str = "px", colour="wide",
              width: int = 280, height: int = 150) -> np.ndarray:
    """Counts of ``values`` in ``bins`` equal bins from 0 to ``upper`` (larger values in the last bin)."""
    counts, _ = np.histogram(np.clip(values, 0, upper), bins=bins, range=(0.0, upper))
    image = canvas(width, height)
    axes = Axes(image, 40, 26, width - 10, height - 24, max(int(counts.max()), 1))
    text(image, title, (40, 16), size=0.42)
    step = (axes.right - axes.left) / bins
    for k, count in enumerate(counts):
        if count:
            cv2.rectangle(image, (int(axes.left + k * step) + 1, axes.y(count)),
                          (int(axes.left + (k + 1) * step) - 1, axes.bottom), bgr(colour), -1)
    for tick in nice_ticks(upper, 5):
        if tick <= upper:
            x = int(axes.left + (axes.right - axes.left) * tick / upper)
            text(image, f"{tick:g}", (x - 8, height - 8), size=0.38, colour="muted")
    text(image, unit, (axes.right - 14, height - 8), size=0.38, colour="muted")
    return image


def encode(image: np.ndarray, fmt: str = ".png", quality: int = 85) -> bytes:
    """The image as PNG (or JPEG with ``fmt=".jpg"``) bytes."""
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if fmt in (".jpg", ".jpeg") else []
    ok, data = cv2.imencode(fmt, image, params)
    if not ok:
        raise RuntimeError(f"OpenCV could not encode the figure as {fmt}")
    return data.tobytes()


def data_uri(image: np.ndarray, fmt: str = ".png", quality: int = 85) -> str:
    """An ``<img src>`` value embedding the image (report.html is one self-contained file)."""
    mime = "image/jpeg" if fmt in (".jpg", ".jpeg") else "image/png"
    return f"data:{mime};base64," + base64.b64encode(encode(image, fmt, quality)).decode("ascii")
