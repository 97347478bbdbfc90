"""report.html: one self-contained page (inline CSS, SVG and base64 PNG; no scripts, no external resources)."""

from __future__ import annotations

import html
import logging
from pathlib import Path

import numpy as np
import pycolmap

from rigsfm.core import charts
from rigsfm.core.names import ImageName, name_of
from rigsfm.core.residuals import reprojection_errors
from rigsfm.core.summary import BANDS_WITH_NARROW, Summary, floor_from_markers_alone
from rigsfm.core.workspace import Workspace, model_fingerprint
from rigsfm.inspect.report.figures import (
    JPEG_QUALITY,
    epipolar_figure,
    floor_map_svg,
    read_image,
    topdown_svg,
)

logger = logging.getLogger(__name__)

CSS = """
body{font-family:system-ui,-apple-system,'Segoe UI',sans-serif;margin:24px;color:#222;max-width:1200px}
h1{font-size:22px}h2{font-size:18px;margin-top:32px;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:13px;margin:8px 0}td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}.warn{color:#b00;font-weight:bold}.note{color:#555;font-size:13px}
.hists{display:flex;flex-wrap:wrap;gap:10px}.mono{font-family:ui-monospace,monospace;font-size:11px;white-space:pre}
figure{margin:12px 0}figcaption{font-size:13px;color:#444}
"""


def esc(value) -> str:
    return html.escape(str(value))


def fmt(value, digits: int = 4) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}g}" if abs(value) < 1e4 else f"{value:.1f}"
    return esc(value)


def table(header: list[str], rows: list[list], left: int = 1) -> str:
    head = "".join(f'<th class="{"l" if k < left else ""}">{esc(h)}</th>' for k, h in enumerate(header))
    body = "".join("<tr>" + "".join(f'<td class="{"l" if k < left else ""}">{c}</td>' for k, c in enumerate(row))
                   + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def summary_section(summary: Summary | None, reconstruction: pycolmap.Reconstruction, narrow: dict) -> str:
    parts = ["<h2>Summary</h2>"]
    if summary is None:
        parts.append('<p class="warn">summary.json is missing (the run did not finish: re-run the same command to '
                     "finish it): scale and timings are not shown.</p>")
    rigs = sorted({name_of(im).rig for im in reconstruction.images.values()})
    counts = {s: sum(im.has_pose and name_of(im).sensor == s for im in reconstruction.images.values())
              for s in ("wide", "narrow")}
    registered = summary.registered if summary else {}
    rows: list[list] = [["rigs", len(rigs)], ["3D points", reconstruction.num_points3D()],
            ["metric", esc(narrow.get("metric")) + f" ({esc(narrow.get('units'))})"]]
    for sensor in ("wide", "narrow"):
        total = registered[sensor].total if sensor in registered else "?"
        rows.append([f"{sensor} images registered", f"{counts[sensor]} / {total}"])
    if summary:
        sigma = summary.scale.relative_sigma_percent
        rows.append(["scale source", esc(summary.scale.source) + ("" if sigma is None else f" (±{sigma:.3g} %)")])
        rows.append(["mapper", esc(summary.mapping.used or "?")])
        rows.append(["mean reprojection error (px)", fmt(summary.mean_reprojection_error_px)])
        rows.append(["images folder", esc(summary.inputs.images)])
    parts.append(table(["", ""], rows))
    for warning in summary.warnings if summary else []:
        parts.append(f'<p class="warn">warning: {esc(warning)}</p>')
    if summary and summary.scale.measurements:
        parts.append("<h3>Scale measurements</h3>")
        parts.append(table(["measurement", "kind", "true (m)", "reconstructed (m)", "residual (m)", "residual (%)",
                            "σ (m)"],
                           [[esc(m["label"]), esc(m["kind"]), fmt(m["meters"], 6), fmt(m["reconstructed_meters"], 6),
                             fmt(m["residual_meters"], 3), fmt(m["residual_percent"], 3), fmt(m["sigma_meters"], 3)]
                            for m in summary.scale.measurements], left=2))
    if summary and summary.timings_s:
        timings = summary.timings_s
        parts.append("<h3>Timings (s)</h3>" + table(list(timings), [[fmt(v, 3) for v in timings.values()]], left=0))
    return "".join(parts)


def reprojection_section(reconstruction: pycolmap.Reconstruction) -> str:
    per_camera: dict[str, list[np.ndarray]] = {}
    for name, errors in reprojection_errors(reconstruction).items():
        per_camera.setdefault(ImageName.parse(name).camera, []).append(errors)
    rows, figures = [], []
    merged = {k: np.concatenate(v) for k, v in sorted(per_camera.items())}
    unprojectable = {k: int(np.sum(~np.isfinite(e))) for k, e in merged.items()}  # behind the camera, beyond its lens
    merged = {k: e[np.isfinite(e)] for k, e in merged.items()}
    observed = [e for e in merged.values() if e.size]
    upper = float(np.percentile(np.concatenate(observed), 99)) * 1.2 if observed else 1.0
    upper = max(upper, 0.1)
    for camera, e in merged.items():
        rows.append([esc(camera), e.size, fmt(float(e.mean())) if e.size else "–",
                     fmt(float(np.sqrt(np.mean(e**2)))) if e.size else "–",
                     fmt(float(np.percentile(e, 95))) if e.size else "–", unprojectable[camera]])
        if e.size:
            colour = "narrow" if camera.endswith("/narrow") else "wide"
            figures.append(f'<img alt="reprojection errors of {esc(camera)}" '
                           f'src="{charts.data_uri(charts.histogram(e, camera, upper, colour=colour))}">')
    return ("<h2>Reprojection error per camera</h2>"
            + table(["camera", "observations", "mean (px)", "RMS (px)", "95th pct (px)",
                     "not projectable"], rows)
            + '<p class="note">Narrow images are matched after a first adjustment where they carry texture (--narrow '
              "auto); homogeneous views give no usable matches: a narrow camera without observations takes its pose "
              "from its wide camera through E^sl.</p>"
            + f'<div class="hists">{"".join(figures)}</div>')


def pairs_section(narrow: dict) -> str:
    rows = []
    for p in narrow.get("pairs", []):
        e, d = p["euler_zyx_deg"], p["centre_direction_in_i"]
        distance = p.get("distance_m", p.get("distance_units"))
        f = np.asarray(p["F_ji"])
        rows.append([esc(p["i"]), esc(p["j"]), f"{e['yaw']:.4f}", f"{e['pitch']:.4f}", f"{e['roll']:.4f}",
                     "(" + ", ".join(f"{v:.4f}" for v in d) + ")", fmt(distance, 6),
                     fmt(p.get("epipolar_band_95_px"), 3),
                     '<span class="mono">' + "\n".join(" ".join(f"{v:+.3e}" for v in row) for row in f) + "</span>"])
    unit = "m" if narrow.get("metric") else "units"
    return ("<h2>Narrow camera pairs</h2>"
            '<p class="note">narrow_j_from_narrow_i as Euler angles (yaw, pitch, roll; R = Rz Ry Rx, degrees), '
            "unit direction from centre i to centre j in camera i's frame, centre distance, the 95 % epipolar "
            "band half-width (pixels of j), and F_ji (x_j^T F_ji x_i = 0, COLMAP pixels of undistorted images, "
            "scaled to unit norm).</p>"
            + table(["narrow i", "narrow j", "yaw", "pitch", "roll", "centre direction in i", f"distance ({unit})",
                     "band 95 % (px)", "F_ji"], rows, left=2))


def _translation(change: dict, what: str, metric: bool) -> float | None:
    """E^sl's translation ``change`` or ``sigma`` of a refined_calibration row, in mm where ``metric``, else in the
    mapper's unit (summaries of older runs without a scale wrote its thousandths under the _mm key)."""
    if metric:
        return change.get(f"narrow_from_wide_translation_{what}_mm")
    units, thousandths = (change.get(f"narrow_from_wide_translation_{what}_{u}") for u in ("units", "mm"))
    return units if units is not None or thousandths is None else thousandths / 1000.0


def uncertainty_section(narrow: dict, summary: Summary | None = None) -> str:
    u = summary.uncertainty if summary else None
    metric = bool(narrow.get("metric"))
    parts, calibration = ["<h2>Uncertainty</h2>"], []
    if u is None or u.covariance is None:
        parts.append('<p class="warn">No joint covariance of poses and calibration could be estimated: no bands.</p>'
                     if u is not None else '<p class="note">summary.json has no uncertainty record.</p>')
    else:
        how = ("the posterior of the bundle adjustment that refined the calibration with rigs.yaml's sigmas as priors"
               if u.covariance == "posterior" else
               "the image noise of the rig poses plus rigs.yaml's calibration uncertainty pushed through the poses' "
               "sensitivity to it (the calibration was held fixed)")
        floor = {"floor_fit": "the floor the world stage fitted",
                 "known_lengths": "the floor through scale.yaml's known lengths",
                 "points": "the floor found in the sparse points"}.get(u.floor, "no floor found: points at every depth")
        parts.append(
            f'<p class="note">From the joint covariance of rig poses, intrinsics and E^sl: {how}; image noise '
            f"{fmt(u.pixel_sigma_px, 3)} px (weighting)"
            + ("; the bands re-adjust the network over 40 calibration draws (a small network answers a calibration "
               "error far from linearly)" if u.bands == "sampled" else "")
            + ("; of the adjustment with the narrow images' observations (they fix E^sl and the narrow intrinsics: "
               "a band of a pixel or less, which the checks below widen by the keypoints' own noise)"
               if u.bands_from == BANDS_WITH_NARROW else "")
            + f". The 95 % band holds the true correspondence of a point of "
            f"narrow image i with 95 % probability, pooled over the analysis points ({floor}) and over that "
            "covariance: calibrated, not a bound. The calibration's error is one draw per pair, so a single pair may "
            "hold fewer of its points: the last column is the model's probability that fewer than 85 % do. Camera "
            "uncertainties are 1 sigma (root of the trace of the 3x3 covariance) relative to the network as a whole "
            "(its mean centre and orientation held).</p>")
        if u.narrow:
            # without a scale there is no millimetre to claim: the mapper's unit
            parts.append(table(["narrow camera", "centre σ (mm)" if metric else "centre σ (units)",
                                "rotation σ (deg)"],
                               [[esc(name), fmt(v.centre_sigma_mm if metric else v.centre_sigma_in_model_units(), 3),
                                 fmt(v.rotation_sigma_deg, 3)] for name, v in sorted(u.narrow.items())]))
        if u.refined_calibration:
            rows = [[esc(camera), fmt(c.get("focal_change_percent"), 3), fmt(c.get("principal_point_change_px"), 3),
                     fmt(c.get("narrow_from_wide_rotation_change_deg"), 3),
                     fmt(c.get("narrow_from_wide_rotation_sigma_deg"), 3),
                     fmt(_translation(c, "change", metric), 3), fmt(_translation(c, "sigma", metric), 3),
                     "yes" if c.get("observed") else "no"]
                    for camera, c in sorted(u.refined_calibration.items())]
            unit = "mm" if metric else "units"
            calibration.append("<h3>Calibration refined from rigs.yaml</h3>" + table(
                ["camera", "focal change (%)", "principal point change (px)", "E^sl rotation change (deg)",
                 "E^sl rotation σ (deg)", f"E^sl translation change ({unit})", f"E^sl translation σ ({unit})",
                 "observed by images"], rows))
    ranges = {(p["i"], p["j"]): p for p in narrow.get("pairs", [])}
    rows = []
    for pair in (u.pairs if u is not None else []):
        extra = ranges.get((pair.i, pair.j), {})
        depth = extra.get("epipolar_band_depth_range_m")
        rows.append([esc(pair.i), esc(pair.j), fmt(pair.band_px, 3), esc(pair.points or "–"),
                     "–" if not depth else "{:.3g} – {:.3g}".format(*depth), fmt(pair.predicted_below_85, 2)])
    if rows:
        parts.append("<h3>Epipolar band per pair</h3>" + table(
            ["narrow i", "narrow j", "band 95 % (px)", "analysis points",
             f"their depths in i ({'m' if narrow.get('metric') else 'units'})",
             "P(pair < 85 % inside)"], rows, left=2))
    decisions = summary.calibration_decisions if summary else []
    if decisions:  # which rigs' calibration the images informed enough to refine, and why the others were held
        calibration.insert(0, "<h3>Calibration held or refined</h3>" + table(
            ["rig", "calibration", "why"],
            [[esc(d["rig"]), "held at rigs.yaml" if d["held"] else "refined", esc(d["reason"])]
             for d in decisions], left=3))
    return "".join(parts + calibration)


MAX_FIGURES = 12  # ~0.1 MB each as JPEG: the report stays < 5 MB at 16 rigs (120 narrow pairs)


def choose_figures(pairs: list[dict], max_figures: int = MAX_FIGURES) -> dict[tuple[str, str], str]:
    """The pairs worth a figure when there are more than ``max_figures``: half the widest 95 % bands (the least
    certain pairs, the ones to check) and half the narrowest (the best the network does); pair -> why drawn."""
    if len(pairs) <= max_figures:
        return {(p["i"], p["j"]): "" for p in pairs}
    known = sorted((p for p in pairs if p.get("epipolar_band_95_px") is not None),
                   key=lambda p: p["epipolar_band_95_px"])
    unknown = [p for p in pairs if p.get("epipolar_band_95_px") is None]
    widest = known[::-1][: (max_figures + 1) // 2]
    chosen = {(p["i"], p["j"]): "widest band" for p in widest}
    for p in known + unknown:
        if len(chosen) >= max_figures:
            break
        chosen.setdefault((p["i"], p["j"]), "narrowest band" if p in known else "no band")
    return chosen


def epipolar_section(out: Path, summary: Summary | None, reconstruction: pycolmap.Reconstruction, narrow: dict,
                     max_figures: int = MAX_FIGURES) -> str:
    parts = ["<h2>Epipolar check</h2>",
             '<p class="note">Left: distinctive points (strongest corners, else a grid) in narrow image i. '
             "Right: their epipolar lines in narrow image j (drawn through the full camera model, so slightly "
             "curved by distortion) with the 95 % band shaded. The same scene point must lie on its line.</p>"]
    images_dir = Path(summary.inputs.images) if summary and summary.inputs.images else None
    if images_dir is None or not images_dir.is_dir():
        parts.append(f'<p class="warn">Images folder {esc(images_dir)} not found: no epipolar figures.</p>')
        return "".join(parts)
    pairs = narrow.get("pairs", [])
    chosen = choose_figures(pairs, max_figures)
    if len(chosen) < len(pairs):
        parts.append(f'<p class="note">{len(chosen)} of {len(pairs)} pairs are drawn: the widest 95 % bands (the '
                     "least certain pairs, the ones to check) and the narrowest; every pair is listed in the table "
                     "after the figures.</p>")
    for p in pairs:
        if (p["i"], p["j"]) not in chosen:
            continue
        image_i, image_j = (reconstruction.find_image_with_name(n) for n in (p["i"], p["j"]))
        if image_i is None or image_j is None:
            continue
        pixels = [read_image(images_dir / n) for n in (p["i"], p["j"])]
        if any(x is None for x in pixels):
            parts.append(f'<p class="warn">cannot read {esc(p["i"])} or {esc(p["j"])} in {esc(images_dir)}</p>')
            continue
        j_from_i = image_j.cam_from_world() * image_i.cam_from_world().inverse()
        figure = epipolar_figure(pixels[0], pixels[1],  # type: ignore[arg-type]  # both read: checked above
                                 reconstruction.cameras[image_i.camera_id],
                                 reconstruction.cameras[image_j.camera_id], j_from_i, p.get("epipolar_band_95_px"))
        band = p.get("epipolar_band_95_px")
        caption = (f"{esc(p['i'])} → {esc(p['j'])}" + ("" if band is None else f"; band ±{band:.2f} px")
                   + (f" ({chosen[(p['i'], p['j'])]})" if chosen[(p['i'], p['j'])] else ""))
        parts.append(f'<figure><img alt="epipolar check {esc(p["i"])} to {esc(p["j"])}" '
                     f'src="{charts.data_uri(figure, ".jpg", JPEG_QUALITY)}"><figcaption>{caption}</figcaption>'
                     '</figure>')
    if len(chosen) < len(pairs):
        rows = [[esc(p["i"]), esc(p["j"]), fmt(p.get("epipolar_band_95_px"), 3),
                 esc(chosen.get((p["i"], p["j"]), "–"))] for p in pairs]
        parts.append(table(["narrow i", "narrow j", "band 95 % (px)", "drawn"], rows, left=2))
    return "".join(parts)


def world_section(narrow: dict, reconstruction: pycolmap.Reconstruction) -> str:
    world = narrow.get("world")
    parts = ["<h2>World frame and floor map</h2>"]
    if not world:
        parts.append('<p class="note">This result predates the floor frame (no "world" in narrow_poses.json).</p>')
        return "".join(parts)
    floor = world.get("floor") or {}
    if world.get("frame") != "floor":
        why = ("--world mapping was asked for" if world.get("asked") == "mapping"
               else f"no floor was found: {floor.get('reason', '?')}")
        parts.append(f'<p class="note">The poses are in the mapper\'s frame ({esc(why)}): no metres on the ground.</p>')
        return "".join(parts)
    matching = floor.get("matching") or {}
    heights = floor.get("camera_height") or {}
    by_source = floor.get("points_by_source") or {}
    rows = [["z", esc(world.get("z_axis"))], ["origin", esc(world.get("origin"))], ["x", esc(world.get("x_axis"))],
            ["floor points", ", ".join(f"{esc(k)} {v}" for k, v in by_source.items())]]
    if floor_from_markers_alone(by_source, floor.get("num_points")):
        rows += [["floor from", "the known-length markers alone (no floor fitted the points)"],
                 # one bar: the tilt about it is the cameras' up's, from their rolls' scatter (docs/world.md)
                 ["normal σ from the cameras' rolls, or the markers' scatter with two bars apart (deg)",
                  fmt(floor.get("normal_sigma_deg"), 3)]]
    else:
        rows += [["fit residual RMS (m)", fmt(floor.get("rms"))],
                 # with each image pair's points sharing its pose error (docs/world.md); older results: the scatter
                 ["normal σ (deg)" if floor.get("sigma_basis") else "normal σ of the points' scatter (deg; a lower bound)",
                  fmt(floor.get("normal_sigma_deg"), 3) + (f" ({esc(floor['sigma_basis'])})"
                                                           if floor.get("sigma_basis") else "")]]
    rows += [["camera height σ from the floor (m; the largest)", fmt(floor.get("camera_height_sigma"), 3)],
             ["camera heights (m)", f"{fmt(heights.get('min'))} – {fmt(heights.get('max'))}"],
             ["floor matching", "not needed (the sparse points fix the floor)" if not matching.get("ran") else
              f"{matching.get('rounds')} round(s), {matching.get('image_pairs')} image pairs, "
              f"{matching.get('matched_points')} points, {fmt(matching.get('seconds'), 3)} s "
              f"({esc(matching.get('why'))})"]]
    if floor.get("marker_residuals"):
        rows.append(["marker heights (m)", ", ".join(f"{v:+.4f}" for v in floor["marker_residuals"])])
    parts.append(table(["", ""], rows))
    svg = floor_map_svg(narrow, reconstruction)
    if svg:
        parts.append(svg)
    ground = narrow.get("ground") or {}
    planes = ground.get("plane_heights_m") or []
    if planes:
        seen = ground.get("seen_by_two_or_more_m2") or []
        parts.append('<p class="note">Area seen by two or more narrow cameras: '
                     + ", ".join(f"{fmt(a, 4)} m² at z = {h:g} m" for h, a in zip(planes, seen)) + ".</p>")
        header = ["narrow camera", "height (m)"]
        for h in planes:
            header += [f"footprint (m²) z={h:g}", f"GSD (mm/px) z={h:g}"]
        body = []
        for entry in narrow.get("narrow", []):
            row = [esc(entry["name"]), fmt(float(entry["centre"][2]))]
            for g in entry.get("ground") or []:
                row += [fmt(g.get("footprint_area_m2"), 4), fmt(g.get("gsd_mm_per_px"), 3)]
            body.append(row)
        parts.append(table(header, body))
    return "".join(parts)


def self_check_section(summary: Summary | None) -> str:
    check = summary.epipolar_self_check if summary else None
    parts = ["<h2>Epipolar self-check on synchronised narrow images</h2>",
             '<p class="note">Narrow images of different rigs with the same frame name were taken at the same '
             "instant: features matched between them (searched only near each epipolar line"
             + ("" if not check else f": {esc(check.guided_by)}") +
             ") must lie within the predicted 95 % band. The distances are measured on matches searched in a band "
             f"at least {esc(check.settings.wide_factor if check else 5)}x wider than the "
             "prediction, widened until the matches stay well inside it, so a band that is too narrow shows; a "
             "pair fails when the 95th percentile exceeds the band by more than the keypoints' own noise "
             f"({esc(check.settings.keypoint_noise_px if check else 1.0)} px).</p>"]
    if not check:
        parts.append('<p class="note">Not run.</p>')
        return "".join(parts)
    if check.skipped:
        parts.append(f'<p class="note">Nothing checked: {esc(check.skipped)}.</p>')
        return "".join(parts)
    from rigsfm.core.summary import describe_self_check as describe

    pairs = check.pairs
    parts.append(f'<p class="note">{esc(describe(check)[0].upper() + describe(check)[1:])}.</p>')
    if all(p.verdict == "too few matches" for p in pairs):  # a table of empty rows would say nothing more
        parts.append(f'<p class="note">{fmt(check.seconds, 3)} s.</p>')
        return "".join(parts)
    rows = []
    for p in pairs:
        verdict = esc(p.verdict)
        if p.verdict == "failed":
            verdict = f'<span class="warn">{verdict}</span>'
        within = p.within_band
        rows.append([esc(p.frame), esc(p.i), esc(p.j), fmt(p.band_px, 3), p.matches,
                     fmt(p.median_px, 3), fmt(p.p95_px, 3),
                     "–" if within is None else f"{100 * within:.0f} %", fmt(p.measured_within_px, 3),
                     verdict])
    parts.append(table(["frame", "narrow i", "narrow j", "band 95 % (px)", "matches", "median (px)",
                        "95th pct (px)", "within band + noise", "searched within (px)", "verdict"], rows, left=3))
    parts.append(f'<p class="note">{fmt(check.seconds, 3)} s.</p>')
    return "".join(parts)


def render_page(out: Path, summary: Summary | None, reconstruction: pycolmap.Reconstruction, narrow: dict) -> str:
    title = f"rigsfm report: {out.resolve().name}"
    version = summary.rigsfm_version if summary else ""
    units = "m" if narrow.get("metric") else "units"
    body = [f"<h1>{esc(title)}</h1>",
            f'<p class="note">rigsfm {esc(version)}; workspace {esc(out.resolve())}</p>',
            summary_section(summary, reconstruction, narrow),
            reprojection_section(reconstruction),
            "<h2>Network (top view)</h2>" + topdown_svg(
                reconstruction, units=units, floor_frame=(narrow.get("world") or {}).get("frame") == "floor"),
            world_section(narrow, reconstruction),
            pairs_section(narrow), uncertainty_section(narrow, summary),
            epipolar_section(out, summary, reconstruction, narrow), self_check_section(summary)]
    workspace = Workspace(out)
    tracked = workspace.track.poses_json.is_file()  # `rigsfm track` results, when there are any
    associated = any(workspace.associate.glob("*/persons.json"))  # `rigsfm associate`'s persons in its default folder
    # both sections compare their results' model with this one: the model's files are read once, not per section
    fingerprint = model_fingerprint(workspace.sparse) if tracked or associated else None
    if tracked:
        from rigsfm.track import track_report_section

        body.append(track_report_section(out, fingerprint))
    if associated:
        from rigsfm.associate.report import associate_report_section

        body.append(associate_report_section(out, fingerprint))
    return ('<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>{''.join(body)}</body></html>\n")
