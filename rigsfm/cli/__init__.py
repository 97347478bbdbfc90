"""The ``rigsfm`` command: a thin typer shell over the library."""

from __future__ import annotations

import functools
import logging
import tempfile
import traceback
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from rigsfm.calibrate.command import calibrate_command
from rigsfm.core.errors import RigsfmError
from rigsfm.inspect.export import export_command
from rigsfm.run.features import Features, MatchingOptions
from rigsfm.run.mapping import Mapper, MappingOptions
from rigsfm.pick import pick_command
from rigsfm.run.pipeline import RunOptions, run
from rigsfm.inspect.report import report_command
from rigsfm.track.command import track_command
from rigsfm.inspect.viewer import view_command

app = typer.Typer(add_completion=False, no_args_is_help=True)
console = Console()
err_console = Console(stderr=True)


def fail_cleanly(command):
    """Turn every ``RigsfmError`` into one red line and exit code 1 (2 for Ctrl-C)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except RigsfmError as error:
            err_console.print(f"[bold red]error:[/] {error}", highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            err_console.print("[bold red]interrupted[/]: re-run the same command to resume")
            raise typer.Exit(2) from None
        except Exception as error:  # a bug, not the user's input: one line, the traceback in a file
            with tempfile.NamedTemporaryFile("w", prefix="rigsfm-error-", suffix=".txt", delete=False) as f:
                traceback.print_exc(file=f)
            err_console.print(f"[bold red]internal error:[/] {type(error).__name__}: {error} "
                              f"(traceback in {f.name}; please report it)", highlight=False, soft_wrap=True)
            raise typer.Exit(3) from None

    return wrapper


def configure_logging(verbose: bool) -> None:
    """rigsfm's own log on the terminal (warnings, or everything with -v); COLMAP's goes to OUT/colmap.log."""
    handler = RichHandler(console=err_console, level=logging.INFO if verbose else logging.WARNING,
                          show_path=False, show_time=False)
    logging.basicConfig(level=logging.INFO, handlers=[handler], format="%(message)s", force=True)


class StageProgress:
    """A rich progress bar per pipeline stage, created on the stage's first report."""

    def __init__(self, progress: Progress):
        self.progress = progress
        self.tasks: dict[str, int] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.progress.add_task(stage, total=total)
        self.progress.update(self.tasks[stage], completed=done, total=total)


def print_summary(summary: dict, out: Path) -> None:
    table = Table(title=f"rigsfm result in {out}", show_lines=False)
    table.add_column("camera")
    table.add_column("observations", justify="right")
    table.add_column("mean reproj. error (px)", justify="right")
    for camera, row in summary["reprojection_error"].items():
        mean = "-" if row["mean_px"] is None else f"{row['mean_px']:.3f}"
        table.add_row(camera, str(row["observations"]), mean)
    console.print(table)
    reg = summary["registered"]
    console.print(
        f"registered: wide {reg['wide']['registered']}/{reg['wide']['total']}, "
        f"narrow {reg['narrow']['registered']}/{reg['narrow']['total']}; "
        f"{summary['num_points3D']} points; scale source: {summary['scale']['source']}"
        + ("" if summary["scale"]["relative_sigma_percent"] is None
           else f" (+-{summary['scale']['relative_sigma_percent']:.3g} %)")
    )
    for row in summary["scale"]["measurements"]:
        console.print(
            f"  {row['label']}: {row['reconstructed_meters']:.4f} m vs {row['meters']:.4f} m "
            f"({row['residual_percent']:+.3f} %)"
        )
    console.print("timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in summary["timings_s"].items()))
    for warning in summary["warnings"]:
        console.print(f"[bold yellow]warning:[/] {warning}")


def print_manual_matches(report: dict) -> None:
    table = Table(title=f"manual matches ({report['file']})")
    for column in ("image a", "image b", "given", "kept (inliers)", "automatic inliers", "verified after"):
        table.add_column(column, justify="left" if column.startswith("image") else "right")
    for pair in report["pairs"]:
        table.add_row(pair["image_a"], pair["image_b"], str(pair["given"]), str(pair["kept"]),
                      str(pair["automatic_inliers"]), str(pair["inliers_after"]))
    console.print(table)
    for pair in report["pairs"]:
        for row in pair["rejected"]:
            error = "-" if row["epipolar_error_px"] is None else f"{row['epipolar_error_px']:.1f} px"
            console.print(f"  rejected line {row['line']}: {pair['image_a']} ({row['xy_a'][0]:.1f}, "
                          f"{row['xy_a'][1]:.1f}) <-> {pair['image_b']} ({row['xy_b'][0]:.1f}, {row['xy_b'][1]:.1f}),"
                          f" epipolar error {error}", highlight=False)


@app.command("run")
@fail_cleanly
def run_command(
    images: Annotated[Path, typer.Argument(help="IMAGES/<rig>/<wide|narrow>/<frame file>")],
    rigs: Annotated[Path, typer.Option("--rigs", help="rigs.yaml: intrinsics and narrow_from_wide per rig")],
    out: Annotated[Path, typer.Option("--out", help="output workspace folder")],
    scale: Annotated[Optional[Path], typer.Option("--scale", help="scale.yaml with metric measurements")] = None,
    mapper: Annotated[Mapper, typer.Option("--mapper")] = Mapper.INCREMENTAL,
    narrow_features: Annotated[bool, typer.Option("--narrow-features", help="also match narrow images")] = False,
    features: Annotated[Features, typer.Option("--features", help="asift: affine-robust, for large perspective "
                                               "changes between rigs (slower)")] = Features.SIFT,
    manual_matches: Annotated[Optional[Path], typer.Option(
        "--manual-matches", help="CSV image_a,x_a,y_a,image_b,x_b,y_b of hand-picked correspondences between "
        "wide images (COLMAP pixels); see `rigsfm pick`")] = None,
    max_ratio: Annotated[float, typer.Option("--max-ratio", help="Lowe ratio test threshold")] = 0.8,
    cross_check: Annotated[bool, typer.Option("--cross-check/--no-cross-check", help="mutual matching")] = True,
    rig_verification: Annotated[Optional[bool], typer.Option(
        "--rig-verification/--no-rig-verification",
        help="verify pairs of frames as rigs [default: on, off with --narrow-features]")] = None,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing result")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Metric poses of every narrow camera of a hybrid-rig network, from image folders."""
    configure_logging(verbose)
    options = RunOptions(
        matching=MatchingOptions(max_ratio=max_ratio, cross_check=cross_check,
                                 rig_verification=rig_verification, narrow_features=narrow_features,
                                 features=features),
        mapping=MappingOptions(mapper=mapper, seed=seed),
        overwrite=overwrite,
        manual_matches=manual_matches,
    )
    with Progress(TextColumn("{task.description:<15}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as progress:
        result = run(images, rigs, out, scale, options, progress=StageProgress(progress))
    print_summary(result.summary, out)
    if "manual_matches" in result.summary:
        print_manual_matches(result.summary["manual_matches"])


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


@app.command("demo")
@fail_cleanly
def demo_command(
    out: Annotated[Path, typer.Argument(help="folder for the rendered scene, the run and accuracy.json")],
    num_rigs: Annotated[int, typer.Option("--num-rigs", min=2)] = 8,
    arc_deg: Annotated[float, typer.Option("--arc-deg", help="angular span of the rigs; 360 = full circle")] = 360.0,
    image_scale: Annotated[float, typer.Option("--image-scale", help="0.5 renders 812x617 images")] = 1.0,
    exact_calibration: Annotated[bool, typer.Option("--exact-calibration", help="no calibration errors")] = False,
    mapper: Annotated[Mapper, typer.Option("--mapper")] = Mapper.INCREMENTAL,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite")] = False,
) -> None:
    """Render a synthetic full circle of hybrid rigs, reconstruct it, and print accuracy vs ground truth."""
    configure_logging(False)
    from rigsfm.synth.demo import run_demo
    from rigsfm.synth.scene import SceneOptions

    scene = SceneOptions(num_rigs=num_rigs, arc_deg=arc_deg, image_scale=image_scale, seed=seed,
                         calibration_noise=not exact_calibration)
    options = RunOptions(mapping=MappingOptions(mapper=mapper, seed=seed), overwrite=overwrite)
    with Progress(TextColumn("{task.description:<15}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console) as progress:
        result = run_demo(out, scene, options, progress=StageProgress(progress))
    print_summary(result.run.summary, out / "run")
    print_accuracy(result.accuracy)
    console.print(f"scene: {out / 'scene'}   result: {out / 'run'}   accuracy: {out / 'accuracy.json'}")


app.command("calibrate")(fail_cleanly(calibrate_command))
app.command("report")(fail_cleanly(report_command))
app.command("view")(fail_cleanly(view_command))
app.command("export")(fail_cleanly(export_command))
app.command("pick")(fail_cleanly(pick_command))
app.command("track")(fail_cleanly(track_command))


@app.callback()
def main() -> None:
    """rigsfm: metric calibration of hybrid (wide + narrow) stereo-rig networks."""
