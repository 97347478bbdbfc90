"""``rigsfm run`` and ``rigsfm demo``."""

from __future__ import annotations

import shlex
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from rigsfm.cli.common import (
    StageProgress,
    configure_logging,
    console,
    fail_cleanly,
    finish,
    flag,
    progress_bars,
)
from rigsfm.core.summary import ManualMatchesSummary, floor_from_markers_alone
from rigsfm.inspect.options import ExportFormat
from rigsfm.run.options import (
    GLOBAL_FROM_FRAMES,
    AdjustOptions,
    Calibration,
    Device,
    Executor,
    Features,
    Mapper,
    MappingOptions,
    MatchingOptions,
    NarrowMode,
    Pairs,
    RunOptions,
    SelfCheckOptions,
    WorldFrame,
    WorldOptions,
)

VERBOSE = flag("--verbose", "-v", help="show rigsfm's log (info level) on the terminal")
STRICT = flag("--strict", help="exit with code 4 when the result carries warnings (for scripts)")
MAPPER_HELP = (f"COLMAP's mapper for the wide images; auto: global from {GLOBAL_FROM_FRAMES} wide frames (faster "
               "there, same accuracy), incremental below")


def print_summary(summary, out: Path) -> None:
    table = Table(title=f"rigsfm result in {out}", show_lines=False)
    table.add_column("camera")
    table.add_column("observations", justify="right")
    table.add_column("mean reproj. error (px)", justify="right")
    for camera, row in summary.reprojection_error.items():
        table.add_row(camera, str(row.observations), "-" if row.mean_px is None else f"{row.mean_px:.3f}")
    console.print(table)
    if any(row.observations == 0 and camera.endswith("/narrow") for camera, row in summary.reprojection_error.items()):
        console.print("narrow cameras with no observations ('-'): their poses follow from their wide camera "
                      "through E^sl (--narrow: narrow images without usable texture give none)")
    reg, scale = summary.registered, summary.scale
    console.print(
        f"registered: wide {reg['wide'].registered}/{reg['wide'].total}, "
        f"narrow {reg['narrow'].registered}/{reg['narrow'].total}; "
        f"{summary.num_points3D} points; mapper: {summary.mapping.used}; scale source: {scale.source}"
        + ("" if scale.relative_sigma_percent is None else f" (+-{scale.relative_sigma_percent:.3g} %)")
    )
    for row in scale.measurements:
        console.print(f"  {row['label']}: {row['reconstructed_meters']:.4f} m vs {row['meters']:.4f} m "
                      f"({row['residual_percent']:+.3f} %)")
    print_world(summary)
    print_calibration_decisions(summary.calibration_decisions)
    console.print("timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in summary.timings_s.items()))


def print_calibration_decisions(decisions: list[dict]) -> None:
    """Which rigs' calibration the adjustment refined and which it held at rigs.yaml's values, and why."""
    for held in (False, True):
        rows = [d for d in decisions if d["held"] == held]
        if rows:
            console.print(f"calibration {'held at rigs.yaml' if held else 'refined'}: "
                          + "; ".join(f"{d['rig']} ({d['reason']})" for d in rows))


def print_world(summary) -> None:
    """The result's frame and the epipolar self-check, one line each."""
    world, check = summary.world, summary.epipolar_self_check
    floor = (world.floor if world else None) or {}
    if world and world.frame == "floor":
        heights = floor.get("camera_height") or {}
        low, high = heights.get("min", 0), heights.get("max", 0)
        if floor_from_markers_alone(floor.get("points_by_source"), floor.get("num_points")):  # no fit to show
            unit = " m" if world.units == "metres" else " (the mapper's units: not metric)"
            console.print(f"world: floor frame (from the {floor.get('num_points')} known-length end points alone, tilt "
                          f"sigma {floor.get('normal_sigma_deg', float('nan')):.2g} deg; cameras {low:.2f}-{high:.2f}"
                          f"{unit} above the floor)")
        elif world.units == "metres":
            console.print(f"world: floor frame ({floor.get('num_points')} floor points, RMS {1000 * floor['rms']:.1f} "
                          f"mm; cameras {low:.2f}-{high:.2f} m above the floor)")
        else:  # no scale: a millimetre or a metre would be a claim the result cannot make
            console.print(f"world: floor frame ({floor.get('num_points')} floor points, RMS {floor['rms']:.3g}; "
                          f"cameras {low:.3g}-{high:.3g} above the floor, in the mapper's units: not metric)")
    elif world:
        console.print("world: the mapper's frame" + ("" if world.asked == "mapping" else " (no floor found)"))
    if summary.replaced is not None:
        from rigsfm.run.deliver import describe_changes

        console.print(describe_changes(summary.replaced))
    if check and check.pairs:
        from rigsfm.core.summary import describe_self_check as describe

        console.print(f"epipolar self-check: {describe(check)}")
    if summary.narrow_observations:
        from rigsfm.run.narrow.observations import describe_record

        console.print(describe_record(summary.narrow_observations))
    offsets = summary.frame_offsets
    if offsets is not None and offsets.asked:
        from rigsfm.run.checks.sync import describe_record as describe_offsets

        console.print(describe_offsets(offsets))


def print_manual_matches(report: ManualMatchesSummary) -> None:
    table = Table(title=f"manual matches ({report.file})")
    for column in ("image a", "image b", "given", "kept (inliers)", "automatic inliers", "verified after"):
        table.add_column(column, justify="left" if column.startswith("image") else "right")
    for pair in report.pairs:
        table.add_row(pair.image_a, pair.image_b, str(pair.given), str(pair.kept),
                      str(pair.automatic_inliers), str(pair.inliers_after))
    console.print(table)
    for pair in report.pairs:
        for row in pair.rejected:
            error = "-" if row["epipolar_error_px"] is None else f"{row['epipolar_error_px']:.1f} px"
            console.print(f"  rejected line {row['line']}: {pair.image_a} ({row['xy_a'][0]:.1f}, "
                          f"{row['xy_a'][1]:.1f}) <-> {pair.image_b} ({row['xy_b'][0]:.1f}, {row['xy_b'][1]:.1f}),"
                          f" epipolar error {error}")


@fail_cleanly
def run_command(
    images: Annotated[Path, typer.Argument(metavar="IMAGES", help="image folder: IMAGES/<rig>/<wide|narrow>/<frame file>",
                                           show_default=False)],
    rigs: Annotated[Path, typer.Option("--rigs", help="rigs.yaml: intrinsics and narrow_from_wide per rig",
                                       show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="output workspace folder", show_default=False)],
    scale: Annotated[Path | None, typer.Option(
        "--scale", help="scale.yaml: rangefinder distances and known lengths  [default: none, the result is not "
                        "metric]", show_default=False)] = None,
    mapper: Annotated[Mapper, typer.Option("--mapper", help=MAPPER_HELP)] = Mapper.AUTO,
    narrow: Annotated[NarrowMode, typer.Option(
        "--narrow", help="narrow observations: synchronised narrow images matched along the epipolar band at every "
                         "height a person reaches, after a first adjustment, and adjusted again with them; auto: where "
                         "the narrow images carry texture (a crowd), on: wherever they give matches, off: never")
                  ] = NarrowMode.AUTO,
    narrow_features: Annotated[bool, typer.Option("--narrow-features", hidden=True,
                                                  help="the old name of --narrow on")] = False,
    features: Annotated[Features, typer.Option("--features", help="sift, or asift: affine-robust, for large perspective "
                                                                  "changes between rigs (slower)")] = Features.SIFT,
    manual_matches: Annotated[Path | None, typer.Option(
        "--manual-matches", help="CSV image_a,x_a,y_a,image_b,x_b,y_b of hand-picked correspondences between wide "
                                 "images (COLMAP pixels; see `rigsfm pick`)  [default: none]", show_default=False)] = None,
    max_ratio: Annotated[float, typer.Option("--max-ratio", metavar="RATIO", help="Lowe's ratio test threshold of the SIFT matching, "
                                                                 "in (0, 1]")] = 0.8,
    cross_check: Annotated[bool, typer.Option("--cross-check/--no-cross-check",
                                              help="keep only mutual nearest-neighbour matches")] = True,
    rig_verification: Annotated[bool | None, typer.Option(
        "--rig-verification/--no-rig-verification",
        help="verify matches of two frames with both rigs' cameras at once  [default: on]",
        show_default=False)] = None,
    seed: Annotated[int, typer.Option("--seed", metavar="N", help="random seed of the mapper's RANSAC and sampling")] = 0,
    incremental_time_limit: Annotated[int, typer.Option(
        "--incremental-time-limit", min=0, metavar="SECONDS",
        help="after this long the incremental mapper stops and the global mapper's model is used (with a warning)"
    )] = MappingOptions().incremental_time_limit_s,  # type: ignore[assignment]  # set by default
    world: Annotated[WorldFrame, typer.Option(
        "--world", help="floor: z = 0 on the floor, z up, origin under the rigs' centroid, x towards the first rig; "
                        "mapping: the mapper's frame")] = WorldFrame.FLOOR,
    plane_height: Annotated[float | None, typer.Option(
        "--plane-height", metavar="M", help="also map every narrow image onto the plane this many metres above the floor "
                               "(e.g. 1.7 for heads)  [default: the floor only]", show_default=False)] = None,
    fixed_calibration: Annotated[bool, flag("--fixed-calibration", help="hold rigs.yaml's intrinsics and E^sl "
                                                                        "exactly and fit one scale to scale.yaml "
                                                                        "afterwards, instead of refining them with "
                                                                        "their sigmas and the measurements")] = False,
    pairs: Annotated[Pairs, typer.Option("--pairs", help="image pairs to match: auto (each image's best partners, "
                                                         "found by a cheap first pass) or exhaustive (every pair)")
                     ] = Pairs.AUTO,
    neighbours: Annotated[int, typer.Option("--neighbours", min=1, metavar="N", help="with --pairs auto: partners of other rigs "
                                                                        "matched per image")] = 8,
    executor: Annotated[Executor, typer.Option("--executor", help="feature extraction: local (this machine's cores) "
                                                                  "or ray (one task per image on a Ray cluster)")
                        ] = Executor.LOCAL,
    address: Annotated[str | None, typer.Option(
        "--address", metavar="ADDRESS", help="Ray cluster address, e.g. auto or HEAD:6379 (with --executor ray)  [default: start a local "
                          "Ray instance]", show_default=False)] = None,
    device: Annotated[Device, typer.Option("--device", help="SIFT on: auto (a CUDA GPU when pycolmap is the CUDA "
                                                            "build, rigsfm[gpu], and one is found), cpu or cuda")
                      ] = Device.AUTO,
    frame_offsets: Annotated[str | None, typer.Option(
        "--frame-offsets", metavar="auto|FILE",
        help="unsynchronised rigs: auto estimates each rig's frame offset from the moving crowd and pairs the narrow "
             "frames by time; FILE (yaml 'rig03: 1': rig03's frame k was taken at the others' frame k+1) applies "
             "given ones [default: frame names are simultaneous; checked when the self-check fails]",
        show_default=False)] = None,
    overwrite: Annotated[bool, flag("--overwrite", help="replace an existing result in OUT (features and matches "
                                                        "made with the same settings are reused)")] = False,
    strict: Annotated[bool, STRICT] = False,
    verbose: Annotated[bool, VERBOSE] = False,
) -> None:
    """Metric poses of every narrow camera of a hybrid-rig network, from image folders."""
    configure_logging(verbose)
    from rigsfm.run.pipeline import run

    options = RunOptions(
        matching=MatchingOptions(max_ratio=max_ratio, cross_check=cross_check, rig_verification=rig_verification,
                                 features=features, pairs=pairs,
                                 neighbours=neighbours, device=device),
        mapping=MappingOptions(mapper=mapper, seed=seed, incremental_time_limit_s=incremental_time_limit),
        world=WorldOptions(frame=world, plane_heights=() if plane_height is None else (plane_height,)),
        adjust=AdjustOptions(calibration=Calibration.FIXED if fixed_calibration else Calibration.REFINE),
        self_check=SelfCheckOptions(frame_offsets=frame_offsets),
        narrow=NarrowMode.ON if narrow_features else narrow,
        overwrite=overwrite,
        manual_matches=manual_matches,
        executor=executor,
        address=address,
    )
    with progress_bars() as progress:
        result = run(images, rigs, out, scale, options, progress=StageProgress(progress))
    print_summary(result.summary, out)
    if result.summary.manual_matches:
        print_manual_matches(result.summary.manual_matches)
    console.print(f"result: {out}; open {result.workspace.report}")
    finish(result.summary.warnings, strict)


def print_accuracy(accuracy: dict) -> None:
    table = Table(title="accuracy against ground truth (narrow cameras)")
    table.add_column("metric")
    table.add_column("rigsfm median / max", justify="right")
    table.add_column("oracle median / max", justify="right")
    run_, limit = accuracy["narrow"], accuracy["oracle_narrow"]
    for key, label in (("relative_rotation_deg", "pairwise rotation error (deg)"),
                       ("translation_direction_deg", "translation direction error (deg)"),
                       ("distance_error_percent", "centre distance error (%)")):
        table.add_row(label, f"{run_[key]['median']:.4f} / {run_[key]['max']:.4f}",
                      f"{limit[key]['median']:.4f} / {limit[key]['max']:.4f}")
    centre, centre_limit = accuracy["narrow_centre_error_mm"], accuracy["oracle_narrow_centre_error_mm"]
    if centre["median"] is not None:
        table.add_row("narrow centre error (mm)", f"{centre['median']:.1f} / {centre['max']:.1f}",
                      f"{centre_limit['median']:.1f} / {centre_limit['max']:.1f}")
    table.add_row("narrow registered", f"{run_['registered']}/{run_['total']}",
                  f"{limit['registered']}/{limit['total']}")
    console.print(table)
    console.print("oracle: the same observations adjusted from the true poses with rigs.yaml's calibration held "
                  "fixed: a reference, not a limit (rigsfm refines the calibration, so it can do better)")


@fail_cleanly
def demo_command(
    out: Annotated[Path, typer.Argument(metavar="OUT", help="folder for the rendered scene, the run and accuracy.json",
                                        show_default=False)],
    num_rigs: Annotated[int, typer.Option("--num-rigs", min=2, metavar="N", help="rigs round the arena")] = 8,
    arc_deg: Annotated[float, typer.Option("--arc-deg", min=1.0, max=360.0, metavar="DEG",
                                           help="angular span of the rigs; 360 = full circle")] = 360.0,
    image_scale: Annotated[float, typer.Option("--image-scale", max=2.0, metavar="FACTOR",
                                               help="image size relative to 1624x1234 (0.5 renders 812x617)")] = 1.0,
    exact_calibration: Annotated[bool, flag("--exact-calibration", help="give the run the exact calibration "
                                                                        "(no calibration errors)")] = False,
    mapper: Annotated[Mapper, typer.Option("--mapper", help=MAPPER_HELP)] = Mapper.AUTO,
    seed: Annotated[int, typer.Option("--seed", metavar="N", help="seed of the rendered scene and of the mapper")] = 0,
    overwrite: Annotated[bool, flag("--overwrite", help="replace an earlier demo in OUT")] = False,
    strict: Annotated[bool, STRICT] = False,
) -> None:
    """Render a synthetic full circle of hybrid rigs, reconstruct it, and print accuracy vs ground truth."""
    configure_logging(False)
    from rigsfm.synth.demo import check_image_scale, run_demo
    from rigsfm.synth.scene import SceneOptions

    check_image_scale(image_scale)

    scene = SceneOptions(num_rigs=num_rigs, arc_deg=arc_deg, image_scale=image_scale, seed=seed,
                         calibration_noise=not exact_calibration)
    options = RunOptions(mapping=MappingOptions(mapper=mapper, seed=seed), overwrite=overwrite)
    with progress_bars() as progress:
        result = run_demo(out, scene, options, progress=StageProgress(progress))
    print_summary(result.run.summary, out / "run")
    print_accuracy(result.accuracy)
    run_dir = out / "run"
    where = shlex.quote(str(run_dir))
    console.print(f"result: {run_dir} (scene: {out / 'scene'}, accuracy against ground truth: {out / 'accuracy.json'})")
    console.print(f"  look at it:  rigsfm view {where}   (without a display: rigsfm view {where} --screenshot view.png)")
    console.print(f"  report:      {result.run.workspace.report}")
    console.print(f"  export it:   rigsfm export {where} --format json   (or {', '.join(f for f in ExportFormat if f != 'json')})")
    finish(result.run.summary.warnings, strict)
