"""Per-rig PNG of the narrow camera's rotation and translation change over time (rigsfm.core.charts)."""

from __future__ import annotations

import numpy as np

from rigsfm.core import charts

WIDTH, PANEL_HEIGHT, TITLE_HEIGHT = 900, 230, 34
VERDICT_COLOURS = {"stable": "good", "shaking": "warn", "moved": "bad"}


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
    image = charts.canvas(WIDTH, TITLE_HEIGHT + 2 * PANEL_HEIGHT)
    verdict = rig["verdict"]["verdict"]
    charts.text(image, f"{name} ({sensor} camera): {verdict}", (78, 23), size=0.65,
                colour=VERDICT_COLOURS.get(verdict, "ink"), bold=True)
    charts.text(image, f"{len(frames)} frames, x: frame index", (WIDTH - 260, 23), colour="muted")
    charts.series_panel(image, TITLE_HEIGHT, PANEL_HEIGHT, rotation, flagged, thresholds["rotation_deg"],
                        "rotation change (deg)", "deg", steps)
    charts.series_panel(image, TITLE_HEIGHT + PANEL_HEIGHT, PANEL_HEIGHT, translation, flagged,
                        thresholds["translation_mm"], "translation change (mm)", "mm", steps)
    return image
