"""Per-rig PNG of the narrow camera's rotation and translation change over time (OpenCV drawing only)."""

from __future__ import annotations

import cv2
import numpy as np

WIDTH, PANEL_HEIGHT, TITLE_HEIGHT = 900, 230, 34
LEFT, RIGHT, TOP, BOTTOM = 78, 20, 26, 34
FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK, GREY, LIGHT = (30, 30, 30), (150, 150, 150), (225, 225, 225)
BLUE, RED, ORANGE, GREEN = (180, 90, 20), (40, 40, 210), (0, 140, 255), (60, 160, 60)
VERDICT_COLOURS = {"stable": GREEN, "shaking": ORANGE, "moved": RED}


def _text(image: np.ndarray, text: str, origin: tuple[int, int], scale: float = 0.45, colour=BLACK,
          thickness: int = 1) -> None:
    cv2.putText(image, text, origin, FONT, scale, colour, thickness, cv2.LINE_AA)


def _ticks(top: float) -> list[float]:
    """About four round tick values from 0 to at least ``top``."""
    raw = top / 4
    magnitude = 10 ** np.floor(np.log10(raw))
    step = min((m * magnitude for m in (1, 2, 2.5, 5, 10) if m * magnitude >= raw), default=raw)
    return [i * step for i in range(int(np.ceil(top / step)) + 1)]


def _panel(image, y0: int, values, flagged, threshold: float, label: str, unit: str, steps: list[int]) -> None:
    x0, x1, top, bottom = LEFT, WIDTH - RIGHT, y0 + TOP, y0 + PANEL_HEIGHT - BOTTOM
    finite = [v for v in values if v is not None]
    ticks = _ticks(max([threshold * 1.5, *finite]) * 1.08)
    y_max = ticks[-1]
    n = len(values)

    def px(i: int) -> int:
        return round(x0 + (x1 - x0) * (0.5 if n == 1 else i / (n - 1)))

    def py(v: float) -> int:
        return round(bottom - (bottom - top) * v / y_max)

    for t in ticks:
        cv2.line(image, (x0, py(t)), (x1, py(t)), LIGHT, 1)
        _text(image, f"{t:g}", (8, py(t) + 4), 0.4, GREY)
    cv2.rectangle(image, (x0, top), (x1, bottom), GREY, 1)
    for xs in range(x0, x1, 14):  # dashed threshold line
        cv2.line(image, (xs, py(threshold)), (min(xs + 7, x1), py(threshold)), RED, 1, cv2.LINE_AA)
    _text(image, f"threshold {threshold:g} {unit}", (x1 - 170, py(threshold) - 5), 0.4, RED)
    for index in steps:
        cv2.line(image, (px(index), top), (px(index), bottom), ORANGE, 2)
    points = [(px(i), py(v)) for i, v in enumerate(values) if v is not None]
    if len(points) > 1:
        cv2.polylines(image, [np.array(points, np.int32)], False, BLUE, 1, cv2.LINE_AA)
    for i, v in enumerate(values):
        if v is None:
            cv2.drawMarker(image, (px(i), bottom - 6), GREY, cv2.MARKER_TILTED_CROSS, 8, 1)
        else:
            cv2.circle(image, (px(i), py(v)), 4, RED if flagged[i] else BLUE, -1, cv2.LINE_AA)
    _text(image, label, (x0, y0 + 18), 0.5)
    for i in sorted({0, n // 2, n - 1}):
        _text(image, str(i), (px(i) - 4, bottom + 16), 0.4, GREY)


def plot_rig(name: str, rig: dict) -> np.ndarray:
    """BGR image: title with verdict, then rotation (deg) and translation (mm) change of the narrow camera
    (the wide camera's when the rig has no narrow calibration) per frame; red dots: flagged frames,
    orange lines: detected steps, grey crosses: frames not registered."""
    frames = rig["frames"]
    sensor = "narrow" if any("narrow" in f for f in frames) else "wide"
    rotation = [f[sensor]["rotation_change_deg"] if sensor in f else None for f in frames]
    translation = [f[sensor]["translation_change_mm"] if sensor in f else None for f in frames]
    flagged = [bool(f.get("flagged")) for f in frames]
    registered = [i for i, f in enumerate(frames) if f["status"] == "registered"]
    steps = [registered[s["index"]] for s in rig["verdict"]["steps"]]
    thresholds = rig.get("thresholds", {"rotation_deg": 0.05, "translation_mm": 5.0})
    image = np.full((TITLE_HEIGHT + 2 * PANEL_HEIGHT, WIDTH, 3), 255, np.uint8)
    verdict = rig["verdict"]["verdict"]
    _text(image, f"{name} ({sensor} camera): {verdict}", (LEFT, 23), 0.65,
          VERDICT_COLOURS.get(verdict, BLACK), 2)
    _text(image, f"{len(frames)} frames, x: frame index", (WIDTH - 260, 23), 0.45, GREY)
    _panel(image, TITLE_HEIGHT, rotation, flagged, thresholds["rotation_deg"], "rotation change (deg)", "deg", steps)
    _panel(image, TITLE_HEIGHT + PANEL_HEIGHT, translation, flagged, thresholds["translation_mm"],
           "translation change (mm)", "mm", steps)
    return image


def encode_png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("OpenCV could not encode the plot as PNG")
    return data.tobytes()
