"""The explorer's state: a finished OUT, the narrow images of one synchronised frame, the labels CSV.

A *person* is one label: its clicks in one frame's narrow images (at most one per image). The first click of a
person (the first row in the CSV) is its anchor: every other click is measured against the anchor's band. Every
change is written to the CSV at once (atomically); rows of other frames and foreign rows are kept.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core.errors import InputError, WorkspaceError
from rigsfm.core.ground import parse_heights  # noqa: F401  (re-exported)
from rigsfm.core.names import ImageName, name_of, quoted
from rigsfm.core.summary import Summary
from rigsfm.core.workspace import Workspace
from rigsfm.explore.geometry import View, band_in_view, floor_trace, triangulate
from rigsfm.explore.labels import (
    ForeignRow,
    ImageDigests,
    Label,
    drop_stale,
    parse_row,
    read_labels,
    save_labels,
    save_record,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ExploreOptions:
    frame: str | None = None  # the frame file name shown first; default: the first synchronised frame
    labels: Path | None = None  # the labels CSV; default OUT/labels.csv
    images: Path | None = None  # IMAGES; default the run's (summary.json inputs.images)
    heights: tuple[float, float] = (0.0, 2.2)  # the band's segment (m above the floor): a person's feet to head
    ticks: tuple[float, ...] = (0.0, 1.0, 1.8)
    click_sigma_px: float = 1.0  # a click's 1-sigma error per coordinate


def click_allowance_px(click_sigma_px: float) -> float:
    """What the two clicks' own errors add (95 %) to a click's distance from the anchor's band, which is geometric
    (a fraction of a pixel where the narrow images fixed the calibration): each click ``click_sigma_px`` per
    coordinate, the anchor's moving its curve in the other narrow view about as much as it moves in its own."""
    return 1.96 * math.sqrt(2.0) * click_sigma_px


class ExploreResult:
    """What the explorer reads from a finished OUT: the narrow views per frame, the bands, the uncertainties."""

    def __init__(self, out: Path, images: Path | None = None, *, need_images: bool = True):
        from rigsfm.run.checks.self_check import synchronised_frames

        self.workspace = Workspace(Path(out))
        self.workspace.require_result()
        self.reconstruction = self.workspace.read_sparse()
        self.narrow_poses = self.workspace.read_narrow_poses()
        world = self.narrow_poses.get("world") or {}
        if world.get("frame") != "floor":
            raise WorkspaceError(f"{self.workspace.root}: the poses are not in the floor frame (no floor was found or "
                                 "--world mapping was asked), so heights above the floor mean nothing; re-run with a "
                                 "floor (known lengths on the floor in scale.yaml)")
        summary = Summary.read(self.workspace.summary) if self.workspace.summary.is_file() else None
        self.frames: dict[str, list[pycolmap.Image]] = {
            frame: sorted(found, key=lambda im: im.name)
            for frame, found in synchronised_frames(self.reconstruction).items()}
        if not self.frames:
            raise InputError(f"'{self.workspace.root}' holds no narrow images of one frame from two or more rigs (the "
                             "explorer shows one synchronised frame: narrow images of several rigs with the same "
                             "file name)")
        self.sizes = {im.name: (self.reconstruction.cameras[im.camera_id].width,
                                self.reconstruction.cameras[im.camera_id].height)
                      for im in self.reconstruction.images.values() if im.has_pose and name_of(im).is_narrow}
        self.bands = {}
        for pair in self.narrow_poses.get("pairs", []):
            band = pair.get("epipolar_band_95_px")
            if band is not None and np.isfinite(band):
                # the run gives the band of i's points in j; the search from j to i uses the same width
                self.bands[(pair["i"], pair["j"])] = self.bands[(pair["j"], pair["i"])] = float(band)
        sigmas = summary.uncertainty.narrow if summary is not None and summary.uncertainty is not None else {}
        self.views: dict[str, View] = {}
        for image in self.reconstruction.images.values():
            if image.name in self.sizes:
                sigma = sigmas.get(image.name)
                self.views[image.name] = View(
                    image.name, self.reconstruction.cameras[image.camera_id], image.cam_from_world(),
                    centre_sigma_m=(sigma.centre_sigma_in_model_units() if sigma is not None else None) or 0.0,
                    rotation_sigma_rad=math.radians(getattr(sigma, "rotation_sigma_deg", None) or 0.0))
        self.pose_uncertainty = bool(sigmas)
        folder = images if images is not None else (Path(summary.inputs.images) if summary and summary.inputs.images
                                                    else None)
        self.images_dir = Path(folder) if folder is not None else None
        if not need_images:
            return
        if folder is None:
            raise InputError(f"{self.workspace.summary} names no IMAGES folder to read the narrow images from; pass "
                             "--images IMAGES (the run's)")
        if not Path(folder).is_dir() and images is not None:
            raise InputError(f"--images {folder} is not a folder; give the run's IMAGES folder")
        if not Path(folder).is_dir():
            raise InputError(f"the narrow images are read from the run's IMAGES folder {folder}, which is not a "
                             "folder here (moved?); pass --images IMAGES")
        self.images_dir = Path(folder)
        for frame_images in self.frames.values():
            missing = [im.name for im in frame_images if not (self.images_dir / im.name).is_file()]
            if missing:
                raise InputError(f"{self.images_dir} lacks {', '.join(missing[:3])}"
                                 f"{' ...' if len(missing) > 3 else ''}; pass --images IMAGES (the run's)")
        self._say_frames_not_shown()

    def _say_frames_not_shown(self) -> None:
        """One warning for the narrow frames beside the run's images that it was not given (a recording associated
        with ``rigsfm associate --poses-from``): the explorer shows the run's own frames only."""
        from rigsfm.inspect.export import frames_not_in_run

        assert self.images_dir is not None
        others = sorted({name.rsplit("/", 1)[1] for name in frames_not_in_run(self.reconstruction, self.images_dir)})
        if others:
            logger.warning("the explorer shows the run's frames only (%s): %d frame(s) beside the run's images that it "
                           "was not given (%s%s) are not shown; their persons are in `rigsfm associate OUT "
                           "DETECTIONS --poses-from FRAME`'s persons.json and floor.png, and to check one by eye give "
                           "its images to `rigsfm run`", ", ".join(list(self.frames)[:3]), len(others),
                           ", ".join(others[:3]), " ..." if len(others) > 3 else "")

    def frame_names(self, frame: str) -> list[str]:
        if frame not in self.frames:
            shown = quoted(list(self.frames)[:8]) + (" ..." if len(self.frames) > 8 else "")
            raise InputError(f"frame {frame!r} has no narrow images of two or more rigs in '{self.workspace.root}'; "
                             f"frames: {shown}")
        return [im.name for im in self.frames[frame]]

    def band(self, name_i: str, xy, name_j: str, index_j: int, heights, ticks):
        return band_in_view(self.views[name_i], xy, self.views[name_j], index_j, self.bands.get((name_i, name_j)),
                            heights, ticks)


class ExploreSession:
    """Thread-safe state behind the page."""

    def __init__(self, out: Path, options: ExploreOptions = ExploreOptions()):
        self.options = options
        self.result = ExploreResult(out, options.images)
        self.frame = options.frame if options.frame is not None else next(iter(self.result.frames))
        self.result.frame_names(self.frame)
        self.csv_path = Path(options.labels) if options.labels is not None else self.result.workspace.labels
        self.lock = threading.Lock()
        self.labels: list[Label] = []
        self.foreign: list[ForeignRow] = []
        self.stale: list[Label] = []  # clicked on other pictures of the same names: left out at the next save
        self.digests = ImageDigests(self.result.images_dir)
        self.backed_up = False  # the CSV as it was (foreign or stale rows) is copied once before the first rewrite
        self._analysed: dict[tuple, dict] = {}
        self.reload()

    def reload(self) -> None:
        labels, foreign = read_labels(self.csv_path, self.result.sizes)
        labels, stale = drop_stale(self.csv_path, labels, self.digests)
        with self.lock:
            self.labels, self.foreign, self.stale = labels, foreign, stale

    # -- geometry -------------------------------------------------------------------------------------------

    def _frame(self, frame: str | None) -> tuple[str, list[str]]:
        frame = self.frame if frame is None else frame
        return frame, self.result.frame_names(frame)

    def bands(self, frame: str | None, view: int, x: float, y: float) -> dict:
        """The bands in every other view of the frame, and the floor trace, of a click in view ``view``."""
        frame, names = self._frame(frame)
        if not 0 <= view < len(names):
            raise InputError(f"view {view} is not one of the {len(names)} views of frame {frame!r}")
        width, height = self.result.sizes[names[view]]
        if not (math.isfinite(x) and math.isfinite(y) and 0 <= x <= width and 0 <= y <= height):
            raise InputError(f"({x:g}, {y:g}) lies outside {names[view]}")
        heights, ticks = self.options.heights, self.options.ticks
        return {"view": view, "xy": [x, y],
                "bands": [self.result.band(names[view], (x, y), n, k, heights, ticks).to_dict()
                          for k, n in enumerate(names) if k != view],
                "floor": floor_trace(self.result.views[names[view]], (x, y), heights, ticks)}

    def person(self, names: list[str], clicks: list[Label]) -> dict:
        """One person's clicks, their distances from the anchor's bands, and the triangulated point (kept per set of
        clicks: a save recomputes only the person that changed)."""
        key = (tuple(names), tuple(clicks))
        if key not in self._analysed:
            self._analysed[key] = self._person(names, clicks)
        return self._analysed[key]

    def _person(self, names: list[str], clicks: list[Label]) -> dict:
        index = {n: k for k, n in enumerate(names)}
        anchor = clicks[0]
        rows = []
        for label in clicks:
            row = {"view": index[label.image], "image": label.image, "xy": [label.x, label.y]}
            if label is not anchor:
                band = self.result.band(anchor.image, (anchor.x, anchor.y), label.image, index[label.image],
                                        self.options.heights, ())
                distance = band.distance((label.x, label.y))
                row["distance_px"] = None if distance is None else round(distance, 2)
                row["band_px"] = None if band.band_px is None else round(band.band_px, 2)
                row["band_units"] = (None if distance is None or not band.band_px
                                     else round(distance / band.band_px, 3))
                noise = click_allowance_px(self.options.click_sigma_px)
                row["outside"] = bool(distance is not None and band.band_px is not None
                                      and distance > band.band_px + noise)
            rows.append(row)
        found: dict[str, object] = {"person": anchor.person, "clicks": rows, "point": None}
        if len(clicks) >= 2:
            views = [self.result.views[c.image] for c in clicks]
            point = triangulate(views, [(c.x, c.y) for c in clicks], self.options.click_sigma_px)
            if point is not None:
                for row, residual in zip(rows, point.residuals_px):
                    row["residual_px"] = round(float(residual), 2)
                found["point"] = {"xyz": np.round(point.xyz, 4).tolist(),
                                  "height_sigma_m": round(point.height_sigma_m, 4),
                                  "covariance": np.round(point.covariance, 8).tolist(),
                                  "floor_ellipse_95": point.floor_ellipse_95()}
        return found

    # -- state and saving -----------------------------------------------------------------------------------

    def _floor_map(self, names: list[str]) -> dict:
        cameras = []
        by_name = {entry["name"]: entry for entry in self.result.narrow_poses.get("narrow", [])}
        for k, name in enumerate(names):
            ground = (by_name.get(name) or {}).get("ground") or []
            floor = next((g for g in ground if abs(float(g.get("plane_height_m", 0.0) or 0.0)) < 1e-9), ground[0]
                         if ground else None)
            cameras.append({"view": k, "centre": np.round(self.result.views[name].centre, 4).tolist(),
                            "footprint": (floor or {}).get("footprint_m")})
        return {"cameras": cameras}

    def state(self, frame: str | None = None) -> dict:
        frame, names = self._frame(frame)
        with self.lock:
            labels = list(self.labels)
            foreign = len(self.foreign)
            stale = len(self.stale)
        persons: dict[str, list[Label]] = {}
        for label in labels:
            if label.image in names:
                persons.setdefault(label.person, []).append(label)
        return {
            "frame": frame,
            "frames": list(self.result.frames),
            "views": [{"name": n, "width": self.result.sizes[n][0], "height": self.result.sizes[n][1]} for n in names],
            "heights": list(self.options.heights),
            "ticks": list(self.options.ticks),
            "click_sigma_px": self.options.click_sigma_px,
            "click_allowance_px": round(click_allowance_px(self.options.click_sigma_px), 2),
            "pose_uncertainty": self.result.pose_uncertainty,
            "csv": str(self.csv_path),
            "foreign_rows": foreign,
            "stale_labels": stale,
            "labels_elsewhere": sum(label.image not in names for label in labels),
            "floor_map": self._floor_map(names),
            "persons": [self.person(names, clicks) for clicks in persons.values()],
        }

    def set_frame_labels(self, frame: str | None, rows) -> dict:
        """Replace this frame's labels by ``rows`` ([{image, x, y, person}, ...], in order) and save the CSV. The
        CSV as it was is copied to a backup first when it holds foreign rows (once per session) or when more than
        one saved label would be lost."""
        frame, names = self._frame(frame)
        if not isinstance(rows, list):
            raise InputError("'labels' must be a list of {image, x, y, person}")
        clean, seen = [], set()
        for k, row in enumerate(rows):
            if not isinstance(row, dict) or set(row) != {"image", "x", "y", "person"}:
                raise InputError(f"label {k + 1}: expected {{image, x, y, person}}, got {row!r}")
            if row["image"] not in names:
                raise InputError(f"label {k + 1}: {row['image']!r} is not a narrow image of frame {frame!r}")
            if not all(isinstance(row[c], (int, float)) and not isinstance(row[c], bool) for c in ("x", "y")):
                raise InputError(f"label {k + 1}: x and y must be numbers")
            try:
                x, y = float(row["x"]), float(row["y"])
            except OverflowError:
                raise InputError(f"label {k + 1}: x and y must be finite numbers") from None
            label, why = parse_row([row["image"], repr(x), repr(y), str(row["person"])], self.result.sizes)
            if label is None or not isinstance(row["person"], str):
                raise InputError(f"label {k + 1}: {why or 'the person must be a text label'}")
            if (label.image, label.person) in seen:
                raise InputError(f"label {k + 1}: {label.person} has two clicks in {label.image}")
            seen.add((label.image, label.person))
            clean.append(label)
        with self.lock:
            kept = [label for label in self.labels if label.image not in names]
            new = {(c.image, c.person, round(c.x, 3), round(c.y, 3)) for c in clean}
            lost = [c for c in self.labels if c.image in names
                    and (c.image, c.person, round(c.x, 3), round(c.y, 3)) not in new]
            backup = self.csv_path.is_file() and (len(lost) > 1 or (bool(self.foreign or self.stale)
                                                                    and not self.backed_up))
            written = save_labels(self.csv_path, kept + clean, self.foreign, backup=backup)
            save_record(self.csv_path, kept + clean, self.digests)
            self.backed_up = self.backed_up or bool(written)
            self.labels, self.stale = kept + clean, []
        logger.info("Saved %d labels of frame %s to %s", len(clean), frame, self.csv_path)
        state = self.state(frame)
        if written is not None:
            state["backup"] = str(written)
        return state


@dataclass(frozen=True)
class CheckResult:
    pairs: int  # labelled pairs with a band
    inside: int
    without_band: int
    foreign_rows: int
    stale: int  # labels clicked on other pictures of the same names (rigsfm.explore.labels), not checked
    per_pair: dict[tuple[str, str], tuple[int, int]]  # camera pair -> (inside, pairs)
    distances: list[dict]

    @property
    def share(self) -> float | None:
        return self.inside / self.pairs if self.pairs else None


def check_labels(out: Path, labels_csv: Path, options: ExploreOptions = ExploreOptions()) -> CheckResult:
    """The share of labelled pairs (two clicks of one person in one frame, in two rigs' narrow images) whose second
    click lies inside the first one's band (between ``options.heights``, the pair's 95 % half-width) widened by the
    two clicks' own noise (:func:`click_allowance_px` of ``options.click_sigma_px``; 0: the bare band)."""
    result = ExploreResult(out, options.images, need_images=False)  # the check needs no pixels
    if not Path(labels_csv).is_file():
        raise InputError(f"labels file {labels_csv} does not exist")
    labels, foreign = read_labels(Path(labels_csv), result.sizes)
    labels, stale = drop_stale(Path(labels_csv), labels, ImageDigests(result.images_dir))
    groups: dict[tuple[str, str], list[Label]] = {}
    for label in labels:
        groups.setdefault((ImageName.parse(label.image).frame, label.person), []).append(label)
    per_pair: dict[tuple[str, str], list[int]] = {}
    distances, without = [], 0
    for clicks in groups.values():
        for a in range(len(clicks)):
            for b in range(a + 1, len(clicks)):
                first, second = sorted((clicks[a], clicks[b]), key=lambda c: c.image)
                rig_i, rig_j = ImageName.parse(first.image).rig, ImageName.parse(second.image).rig
                if rig_i == rig_j:
                    continue
                band = result.band(first.image, (first.x, first.y), second.image, 0, options.heights, ())
                distance = band.distance((second.x, second.y))
                if distance is None or band.band_px is None:
                    without += 1
                    continue
                allowed = band.band_px + click_allowance_px(options.click_sigma_px)
                inside = distance <= allowed
                counts = per_pair.setdefault((f"{rig_i}/narrow", f"{rig_j}/narrow"), [0, 0])
                counts[0] += inside
                counts[1] += 1
                distances.append({"person": first.person, "i": first.image, "j": second.image,
                                  "distance_px": distance, "band_px": band.band_px, "allowed_px": allowed,
                                  "inside": bool(inside)})
    total = sum(c[1] for c in per_pair.values())
    return CheckResult(total, sum(c[0] for c in per_pair.values()), without, len(foreign), len(stale),
                       {k: (v[0], v[1]) for k, v in sorted(per_pair.items())}, distances)

