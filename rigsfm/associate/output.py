"""What ``rigsfm associate`` writes into DIR, one folder per frame (the frame file's stem)::

  DIR/<frame>/persons.csv   one row per (person, detection): person, x_m, y_m, z_m, sigma_x_m, sigma_y_m, sigma_z_m,
                            confidence, views, image, x, y (exactly as given), row (its line in DETECTIONS)
  DIR/<frame>/persons.json  per person: position (world metres), covariance (m^2), score (log-likelihood ratio
                            against clutter), confidence (its logistic: the model's odds, not a measured rate; see
                            docs/world.md), detections [{image, x, y, row}]; unassigned detections;
                            size_cue {used, head_radius_m}: whether the DETECTIONS' radii scored the frame;
                            poses_from, lent_views: the run's frame whose narrow poses --poses-from lent, and to
                            which views (every view of a frame the run was not given);
                            frame_offsets: whether the rigs took their frames together (rigsfm.associate.sync:
                            each rig's offset, the frames tested, the offsets the frames were paired by), null
                            where not checked; the manifest holds the same
  DIR/<frame>/floor.png     top view of the grid below: every narrow footprint at head height (the middle of
                            ``heights``), every person's 95 % ellipse
  DIR/<frame>/density.csv   persons found per m^2 (detected in two views or more: a lower bound of the crowd's
                            density where heads hide one another) on a grid of ``cell_m`` cells from the world
                            origin, over the cells two or more narrow views see at head height and every person
                            found (x_min_m, y_min_m,
                            x_max_m, y_max_m, persons, per_m2, views: how many narrow views see the cell's centre;
                            per_m2 is nan below two, where nobody could be placed)
  DIR/<frame>/density.png   the same grid as an image (grey: fewer than two views)
  DIR/.rigsfm-associate.json  the files written and their SHA-256: what a later ``--overwrite`` may replace
                            (rigsfm.core.owned; the user's own files in DIR are never removed); ``model``: the
                            run's model they were made from (``model_fingerprint``), for report.html
"""

from __future__ import annotations

import csv
import io
import json
import math
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from rigsfm.core import charts
from rigsfm.core.geometry import project_world
from rigsfm.core.ground import footprint
from rigsfm.core.owned import Previous, commit, previous_files, refuse_changed

CHI2_2D_95 = 5.991464547107979  # 95 % of a 2-D normal lies within this squared Mahalanobis distance
MANIFEST = ".rigsfm-associate.json"  # the files rigsfm wrote into DIR and their SHA-256: all --overwrite may remove
LEGACY_MARKER = ".rigsfm-associate"  # what earlier versions wrote instead of a manifest
FRAME_FILES = ("persons.csv", "persons.json", "floor.png", "density.csv", "density.png")


def _legacy_files(dest: Path, present: list[str]) -> list[str]:
    """An earlier version's output (its marker, no manifest): the marker and the files of its layout."""
    if LEGACY_MARKER not in present:
        return []
    return [name for name in present if name == LEGACY_MARKER
            or (len(parts := name.split("/")) == 2 and parts[1] in FRAME_FILES)]


def check_destination(dest: Path, overwrite: bool) -> Previous:
    """What an association into ``dest`` may replace (:func:`rigsfm.core.owned.previous_files`): an earlier
    association's own files, unchanged since."""
    return previous_files(Path(dest), MANIFEST, overwrite=overwrite, option="--out", what="association",
                          legacy=_legacy_files)


def _stem(frame: str) -> str:
    return Path(frame).stem or frame


def refuse_edited(dest: Path, previous: Previous, frames: Iterable[str]) -> None:
    """Before the work: refuse where an earlier association's file that these frames write again was edited."""
    names = {f"{_stem(frame)}/{name}" for frame in frames for name in FRAME_FILES}
    refuse_changed(Path(dest), previous, names, "--out", "association")


def persons_rows(frame) -> list[list]:
    result, views, det = frame.result, frame.views, frame.detections
    rows = []
    # every person's numbers as Python floats at once (the same values; a frame has hundreds of persons)
    conf, points = result.confidence.tolist(), result.points.tolist()
    tracks = _tracks(frame)
    sigmas = np.sqrt(np.diagonal(result.covariances, axis1=1, axis2=2)).tolist()
    found = [det.images[view.name] for view in views]
    numbers = [d.rows.tolist() for d in found]
    for p, held in enumerate(result.members.tolist()):
        x, y, z = points[p]
        sx, sy, sz = sigmas[p]
        members = [(v, i) for v, i in enumerate(held) if i >= 0]
        for v, i in members:
            d = found[v]
            rows.append([p, tracks[p], f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", f"{sx:.4f}", f"{sy:.4f}", f"{sz:.4f}",
                         f"{conf[p]:.4f}", len(members), d.image, d.text[i][0], d.text[i][1], numbers[v][i]])
    return rows


def _tracks(frame) -> list[int]:
    """Each person's track number (its own number where the frame was associated without its recording's)."""
    return frame.track.tolist() if frame.track is not None else list(range(len(frame.result.points)))


def _links(frame) -> tuple[list, list]:
    """Each person's person of the frame before and its link's confidence (None: not linked, or the first frame)."""
    links = frame.links
    if links is None:
        return [None] * len(frame.result.points), [None] * len(frame.result.points)
    earlier = [e if e >= 0 else None for e in links.earlier.tolist()]
    confidence = [round(c, 4) if c == c else None for c in links.confidence.tolist()]  # NaN: not linked
    return earlier, confidence


def persons_json(frame, frame_offsets: dict | None = None) -> dict:
    result, views, det = frame.result, frame.views, frame.detections
    persons = []
    tracks = _tracks(frame)
    earlier, linked = _links(frame)
    used = set()
    found = [det.images[view.name] for view in views]
    # every person's numbers as Python floats at once (the same values and roundings as element by element)
    xys, numbers = [d.xy.tolist() for d in found], [d.rows.tolist() for d in found]
    points, scores = result.points.tolist(), result.scores.tolist()
    covariances, confidence = np.round(result.covariances, 9).tolist(), result.confidence.tolist()
    for p, held in enumerate(result.members.tolist()):
        dets = []
        for v, i in enumerate(held):
            if i >= 0:
                d = found[v]
                dets.append({"image": d.image, "x": xys[v][i][0], "y": xys[v][i][1],
                             "x_text": d.text[i][0], "y_text": d.text[i][1], "row": numbers[v][i]})
                used.add((v, i))
        persons.append({"person": p, "track": tracks[p], "after": earlier[p], "after_confidence": linked[p],
                        "position_m": [round(c, 5) for c in points[p]],
                        "covariance_m2": covariances[p], "score": round(scores[p], 4),
                        "confidence": round(confidence[p], 5), "detections": dets})
    unassigned = [{"image": views[v].name, "row": numbers[v][i]}
                  for v in range(len(views)) for i in range(len(found[v])) if (v, i) not in used]
    return {"frame": frame.frame, "frame_units": "world metres (the run's world frame)",
            "views": [v.name for v in views],
            # the run's frame whose poses and bands stood in for this frame's (--poses-from); null: the run's own
            "poses_from": frame.poses_from,
            # the views whose poses it lent: every view of a frame the run was not given, some of a frame of the run
            # that lacked their narrow images
            "lent_views": list(frame.lent_views),
            "sigma_pose_px": {v.name: round(v.sigma_pose_px, 4) for v in views},
            # the detector's noise per coordinate (px) the persons were found with: --pixel-sigma, or the crowd's
            "pixel_sigma_px": result.pixel_sigma,
            # The crowd's correction of each view (undistorted px, subtracted from its detections) and the band's
            # sigma before it, as this frame's persons were found with them; a zero shift: the view kept the run's pose.
            "shift_px": {name: [round(float(c), 4) for c in shift] for name, shift in result.shift_px.items()},
            "band_sigma_px": {name: round(float(sigma), 4) for name, sigma in result.band_sigma_px.items()},
            # The apparent head radii score only where every view of the frame has them; the crowd's mean head
            # radius, as its persons gave it (null: the cue was off, or too few persons to estimate it from).
            "size_cue": {"used": bool(views) and all(v.radius_px is not None for v in views),
                         "head_radius_m": result.head_radius_m},
            # whether the rigs took their frames together (rigsfm.associate.sync; the same in every frame): the
            # offsets named and those the frames were paired by; null: not checked (--frame-offsets off)
            "frame_offsets": frame_offsets,
            # each person's "after" is the frame before's person it was linked to (null: none, or the first frame),
            # its "track" goes on where that link is likelier right than wrong (rigsfm.associate.trajectories)
            "persons": persons, "unassigned": unassigned}


def cells_seen(images: list[pycolmap.Image], bounds: tuple[float, float, float, float], cell: float,
               height: float) -> np.ndarray:
    """Per cell of the grid over ``bounds`` (rows from y0, columns from x0): how many of the narrow ``images``
    see its centre at ``height`` above the floor (inside the image, in front, where the lens model maps back)."""
    x0, y0, x1, y1 = bounds
    nx, ny = max(1, round((x1 - x0) / cell)), max(1, round((y1 - y0) / cell))
    gx, gy = np.meshgrid(x0 + (np.arange(nx) + 0.5) * cell, y0 + (np.arange(ny) + 0.5) * cell)
    centres = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, height)]
    seen = np.zeros(len(centres), dtype=np.int64)
    for image in images:
        seen += project_world(image.camera, image.cam_from_world(), centres)[1]  # type: ignore[arg-type]
    return seen.reshape(ny, nx)


def grid_cells(images: list[pycolmap.Image], points: np.ndarray, cell: float, height: float,
               known: dict | None = None) -> tuple[tuple[float, float, float, float], np.ndarray, list[np.ndarray]]:
    """The density grid: its extent (the cells whose centres two or more narrow views see at ``height``, where a
    person can be placed, and every person found, on whole cells from the world origin: the same cells in every
    frame of the same cameras), each cell's views (:func:`cells_seen`) and the views' footprints at ``height``.
    ``known``: what earlier calls for the same model's images found (each image's footprint, the cells' views of
    each extent), kept there: a recording's frames of the same cameras compute them once."""
    known = {} if known is None else known
    # what a footprint depends on: its camera and pose (a recording's frames of static rigs share them, with lent
    # poses exactly)
    placed = tuple((str(image.camera.model), image.camera.params.tobytes(), image.camera.width,  # type: ignore[union-attr]
                    image.camera.height,  # type: ignore[union-attr]
                    image.cam_from_world().matrix().tobytes()) for image in images)
    prints = []
    for image, where in zip(images, placed):
        key = ("footprint", where, height)
        if key not in known:
            fp = footprint(image, height)
            known[key] = np.asarray(fp.polygon) if fp is not None and len(fp.polygon) else None
        if known[key] is not None:
            prints.append(known[key])
    corners = np.concatenate([p[:, :2] for p in prints] + [points[:, :2]]) if prints or len(points) \
        else np.zeros((1, 2))
    lo, hi = np.floor(corners.min(axis=0) / cell) * cell, np.ceil(corners.max(axis=0) / cell) * cell
    bounds = (float(lo[0]), float(lo[1]), float(max(hi[0], lo[0] + cell)), float(max(hi[1], lo[1] + cell)))
    extent = ("seen", placed, bounds, cell, height)
    if extent not in known:
        known[extent] = cells_seen(images, bounds, cell, height)
    seen = known[extent]
    twice = np.argwhere(seen >= 2)
    if not len(twice):
        return bounds, seen, prints
    (j0, i0), (j1, i1) = twice.min(axis=0), twice.max(axis=0)
    if len(points):  # a person at the region's edge keeps its cell
        first = np.round((np.floor(points[:, :2].min(axis=0) / cell) * cell - lo) / cell).astype(int)
        last = np.round((np.ceil(points[:, :2].max(axis=0) / cell) * cell - lo) / cell).astype(int) - 1
        i0, j0, i1, j1 = min(i0, first[0]), min(j0, first[1]), max(i1, last[0]), max(j1, last[1])
    x0, y0 = lo + np.array([i0, j0]) * cell
    x1, y1 = lo + np.array([i1 + 1, j1 + 1]) * cell
    return (float(x0), float(y0), float(x1), float(y1)), seen[j0:j1 + 1, i0:i1 + 1], prints


def density_grid(points: np.ndarray, bounds: tuple[float, float, float, float], cell: float,
                 seen: np.ndarray) -> tuple[np.ndarray, list]:
    """Persons per cell over ``bounds`` and the CSV rows; ``seen``: the views seeing each cell
    (:func:`cells_seen`): a cell fewer than two see has no density (nan: nobody could be placed there)."""
    x0, y0, x1, y1 = bounds
    nx, ny = max(1, round((x1 - x0) / cell)), max(1, round((y1 - y0) / cell))
    counts = np.zeros((ny, nx), dtype=np.int64)
    if len(points):
        ix = np.floor((points[:, 0] - x0) / cell).astype(int)
        iy = np.floor((points[:, 1] - y0) / cell).astype(int)
        ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        np.add.at(counts, (iy[ok], ix[ok]), 1)
    # each cell's edges and numbers as Python values at once (the same arithmetic as cell by cell)
    xs = [f"{x:.3f}" for x in (x0 + np.arange(nx + 1) * cell).tolist()]
    ys = [f"{y:.3f}" for y in (y0 + np.arange(ny + 1) * cell).tolist()]
    number, views = counts.tolist(), seen.tolist()
    per_m2 = [[f"{d:.3f}" for d in row] for row in (counts / cell ** 2).tolist()]
    rows = [[xs[i], ys[j], xs[i + 1], ys[j + 1], number[j][i], per_m2[j][i] if views[j][i] >= 2 else "nan", views[j][i]]
            for j in range(ny) for i in range(nx)]
    return counts, rows


def _json_text(data: dict) -> str:
    """JSON with a line per top-level key and per element of its lists: readable, and written by json's C encoder
    (an indented dump costs more than a carried frame's association)."""
    one = json.JSONEncoder(separators=(", ", ": ")).encode  # json.dumps' own encoder, made once

    lines = []
    for key, value in data.items():
        if isinstance(value, list) and value:
            lines.append(f"{one(key)}: [\n  " + ",\n  ".join(one(item) for item in value) + "\n ]")
        else:
            lines.append(f"{one(key)}: {one(value)}")
    return "{\n " + ",\n ".join(lines) + "\n}\n"


def _csv(header: list[str], rows: list[list]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(rows)
    return buffer.getvalue()


def _floor_background(view: charts.MapFrame, bounds, prints: list[np.ndarray]) -> np.ndarray:
    """floor_map's 1 m grid and narrow footprints, cut at the plot's edge."""
    x0, y0, x1, y1 = bounds
    width, height = view.width, view.height
    image = charts.canvas(width, height)
    px = view.px
    for gx in range(math.ceil(x0), math.floor(x1) + 1):
        a, b = px([gx, y0])[0], px([gx, y1])[0]
        cv2.line(image, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), charts.bgr("grid"), 1)
    for gy in range(math.ceil(y0), math.floor(y1) + 1):
        a, b = px([x0, gy])[0], px([x1, gy])[0]
        cv2.line(image, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), charts.bgr("grid"), 1)
    for polygon in prints:
        cv2.polylines(image, [np.round(px(polygon)).astype(np.int32)], True, charts.bgr("narrow"), 1, cv2.LINE_AA)
    blank = charts.canvas(width, height)  # footprints reach far beyond the grid: cut them at its edge
    top, bottom, left, right = view.top, height - view.bottom, view.left, width - view.right
    image[:top], image[bottom + 1:], image[:, :left], image[:, right + 1:] = (
        blank[:top], blank[bottom + 1:], blank[:, :left], blank[:, right + 1:])
    return image


def floor_map(frame, prints: list[np.ndarray], bounds, plane_m: float, size: int = 900,
              known: dict | None = None, trails: list[np.ndarray] | None = None) -> np.ndarray:
    """Top view over ``bounds`` in the run's world (metres on both axes, a scale bar): the narrow footprints
    ``prints`` on the plane ``plane_m`` above the floor and every person's 95 % ellipse. ``known``: the maps
    drawn before without their persons, kept there (a recording's frames of the same cameras share one).
    ``trails``: per person, where its track stood in the last frames up to this one (K x 2 each), drawn as a line."""
    view = charts.MapFrame.fit(bounds, size)
    scale, px = view.scale, view.px
    drawn = ("floor", tuple(float(b) for b in bounds), size, tuple(p.tobytes() for p in prints))
    background = None if known is None else known.get(drawn)
    if background is None:
        background = _floor_background(view, bounds, prints)
        if known is not None:
            known[drawn] = background
    image = background.copy()
    result = frame.result
    if len(result):  # every person's ellipse at once: a recording writes a map per frame
        values, vectors = np.linalg.eigh(result.covariances[:, :2, :2])
        axes = np.maximum(1, np.round(np.sqrt(np.maximum(values, 0) * CHI2_2D_95) * scale)).astype(int)
        angles = -np.degrees(np.arctan2(vectors[:, 1, 1], vectors[:, 0, 1]))
        centres = np.round(px(result.points[:, :2])).astype(int)
        if trails is not None:
            lines = [np.round(px(trail)).astype(np.int32) for trail in trails if len(trail) > 1]
            cv2.polylines(image, lines, False, charts.bgr("link"), 1, cv2.LINE_AA)
        for (cx, cy), (minor, major), angle in zip(centres.tolist(), axes.tolist(), angles.tolist()):
            cv2.ellipse(image, (cx, cy), (major, minor), angle, 0, 360, charts.bgr("wide"), 1, cv2.LINE_AA)
            cv2.circle(image, (cx, cy), 1, charts.bgr("ink"), -1)
    view.draw_axes(image)
    steps = "" if trails is None else f"tracks over up to {TRAIL_FRAMES} frames (green), "
    charts.text(image, f"{frame.frame}: {len(result)} persons; narrow footprints at {plane_m:.2f} m (orange), "
                       f"95 % ellipses (blue), {steps}1 m grid; world metres", (10, 18))
    return image


TRAIL_FRAMES = 10  # the frames a track's trail on floor.png reaches back over: a second of walking at 10 frames/s


def next_trails(trails: dict[int, np.ndarray], frame) -> dict[int, np.ndarray]:
    """Each track of ``frame`` with its last positions on the floor (``trails``: the frame before's, by track;
    a track that goes on extends its trail, a new one starts one); empty where the frame has no tracks."""
    if getattr(frame, "track", None) is None:
        return {}
    points = frame.result.points[:, :2]
    out = {}
    for p, track in enumerate(frame.track.tolist()):
        earlier = trails.get(track)
        out[track] = points[p:p + 1] if earlier is None else np.vstack([earlier[1 - TRAIL_FRAMES:], points[p:p + 1]])
    return out


COLOUR_BAR = (16, 26, 216, 36)  # density.png's colour bar (x0, y0, x1, y1 px): 0 to the frame's largest density


def density_image(counts: np.ndarray, cell: float, seen: np.ndarray, bounds, pixels: int = 24) -> np.ndarray:
    """The density grid over ``bounds`` (its cells of ``cell`` metres, ``pixels`` each) in the run's world, with
    metre axes and a scale bar; grey where fewer than two views see a cell."""
    density = counts / cell ** 2
    top = max(float(density.max()), 1e-9)
    grey = np.uint8(np.clip(density / top * 255, 0, 255))
    cells = cv2.applyColorMap(grey[::-1], cv2.COLORMAP_VIRIDIS)  # type: ignore[index]  # np.uint8(array) is an array
    cells[seen[::-1] < 2] = charts.bgr("grid")
    cells = cv2.resize(cells, (cells.shape[1] * pixels, cells.shape[0] * pixels), interpolation=cv2.INTER_NEAREST)
    legend = 44  # a band above the map for the legend and its colour bar
    x0, y0, x1, y1 = (float(v) for v in bounds)
    view = charts.MapFrame(x0, y0, x1, y1, scale=pixels / cell, top=charts.MapFrame.top + legend)
    image = charts.canvas(max(view.width, 440), view.height)  # the legend's width
    image[view.top:view.top + cells.shape[0], view.left:view.left + cells.shape[1]] = cells
    view.draw_axes(image)
    # the persons found: one hidden or missed in all but one view is not among them (a dense crowd's most)
    charts.text(image, f"persons found per m2 (not the hidden), max {top:.1f}; grey: fewer than 2 narrow views",
                (4, 16), size=0.4)
    ramp = cv2.applyColorMap(np.linspace(0, 255, COLOUR_BAR[2] - COLOUR_BAR[0]).astype(np.uint8)[None, :],
                             cv2.COLORMAP_VIRIDIS)
    x0, y0, x1, y1 = COLOUR_BAR
    image[y0:y1, x0:x1] = np.repeat(ramp, y1 - y0, axis=0)
    charts.text(image, "0", (x0 - 12, y1 - 1), size=0.4, colour="muted")
    charts.text(image, f"{top:.1f} per m2", (x1 + 6, y1 - 1), size=0.4, colour="muted")
    return image


def _png(path: Path, image: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"could not encode {path}")
    path.write_bytes(data.tobytes())


def write_results(dest: Path, model, frames: list, options, previous: Previous | None = None,
                  fingerprint: str | None = None, frame_offsets: dict | None = None) -> Path:
    """Write every frame's files into a temporary folder beside ``dest``, then move them in (``previous``: what
    :func:`check_destination` allowed to replace; ``fingerprint``: the run's model they were made from, recorded in
    the manifest as ``model``)."""
    dest = Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent))
    known: dict = {}  # grid_cells' footprints and cells' views, for the frames after the first
    trails: dict[int, np.ndarray] = {}  # per track, its last positions, which floor.png draws
    try:
        for frame in frames:
            folder = tmp / _stem(frame.frame)
            folder.mkdir()
            height = (options.heights[0] + options.heights[1]) / 2
            placed = [model.images[view.name] for view in frame.views]
            bounds, seen, prints = grid_cells(placed, frame.result.points, options.cell_m, height, known)
            (folder / "persons.csv").write_text(_csv(
                ["person", "track", "x_m", "y_m", "z_m", "sigma_x_m", "sigma_y_m", "sigma_z_m", "confidence", "views",
                 "image", "x", "y", "row"], persons_rows(frame)))
            (folder / "persons.json").write_text(_json_text(persons_json(frame, frame_offsets)))
            counts, rows = density_grid(frame.result.points, bounds, options.cell_m, seen)
            (folder / "density.csv").write_text(_csv(["x_min_m", "y_min_m", "x_max_m", "y_max_m", "persons", "per_m2",
                                                      "views"], rows))
            _png(folder / "density.png", density_image(counts, options.cell_m, seen, bounds))
            trails = next_trails(trails, frame)
            _png(folder / "floor.png", floor_map(frame, prints, bounds, height, known=known,
                                                 trails=[trails[t] for t in frame.track.tolist()]
                                                 if trails and frame.links is not None else None))
        previous = check_destination(dest, True) if previous is None else previous
        commit(dest, tmp, previous, MANIFEST, {"written_by": "rigsfm associate", "model": fingerprint,
                                                "frame_offsets": frame_offsets},
               option="--out", what="association")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)  # the temporary folder made above: only rigsfm's files
    return dest
