"""The ``rigsfm`` command: a thin typer shell over the library."""

from __future__ import annotations

import functools
import logging
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from rigsfm.errors import RigsfmError
from rigsfm.features import MatchingOptions
from rigsfm.mapping import Mapper, MappingOptions
from rigsfm.pipeline import RunOptions, run

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

    return wrapper


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
    )
    for row in summary["scale"]["measurements"]:
        console.print(
            f"  {row['label']}: {row['reconstructed_meters']:.4f} m vs {row['meters']:.4f} m "
            f"({row['residual_percent']:+.3f} %)"
        )
    console.print("timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in summary["timings_s"].items()))
    for warning in summary["warnings"]:
        console.print(f"[bold yellow]warning:[/] {warning}")


@app.command("run")
@fail_cleanly
def run_command(
    images: Annotated[Path, typer.Argument(help="IMAGES/<rig>/<wide|narrow>/<frame file>")],
    rigs: Annotated[Path, typer.Option("--rigs", help="rigs.yaml: intrinsics and narrow_from_wide per rig")],
    out: Annotated[Path, typer.Option("--out", help="output workspace folder")],
    scale: Annotated[Optional[Path], typer.Option("--scale", help="scale.yaml with metric measurements")] = None,
    mapper: Annotated[Mapper, typer.Option("--mapper")] = Mapper.INCREMENTAL,
    narrow_features: Annotated[bool, typer.Option("--narrow-features", help="also match narrow images")] = False,
    max_ratio: Annotated[float, typer.Option("--max-ratio", help="Lowe ratio test threshold")] = 0.8,
    cross_check: Annotated[bool, typer.Option("--cross-check/--no-cross-check", help="mutual matching")] = True,
    rig_verification: Annotated[bool, typer.Option("--rig-verification", help="verify pairs as rigs")] = False,
    seed: Annotated[int, typer.Option("--seed")] = 0,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing result")] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Metric poses of every narrow camera of a hybrid-rig network, from image folders."""
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(levelname)s %(message)s")
    options = RunOptions(
        matching=MatchingOptions(max_ratio=max_ratio, cross_check=cross_check,
                                 rig_verification=rig_verification, narrow_features=narrow_features),
        mapping=MappingOptions(mapper=mapper, seed=seed),
        overwrite=overwrite,
    )
    with Progress(TextColumn("{task.description:<15}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console, transient=False) as progress:
        result = run(images, rigs, out, scale, options, progress=StageProgress(progress))
    print_summary(result.summary, out)


@app.callback()
def main() -> None:
    """rigsfm: metric calibration of hybrid (wide + narrow) stereo-rig networks."""
