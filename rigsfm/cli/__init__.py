"""The ``rigsfm`` command: a thin typer shell over the library, one module per verb.

Only this package imports typer. It imports nothing heavy at start (each command imports its library when
it runs), so ``rigsfm --help`` answers at once.
"""

from __future__ import annotations

import typer

from rigsfm.cli.associate import associate_command
from rigsfm.cli.calibrate import calibrate_command
from rigsfm.cli.inspect import export_command, report_command, view_command
from rigsfm.cli.pick import pick_command
from rigsfm.cli.run import demo_command, run_command
from rigsfm.cli.track import track_command

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  context_settings={"help_option_names": ["-h", "--help"]})

app.command("calibrate")(calibrate_command)
app.command("run")(run_command)
app.command("report")(report_command)
app.command("view")(view_command)
app.command("export")(export_command)
app.command("pick")(pick_command)
app.command("track")(track_command)
app.command("demo")(demo_command)
app.command("associate")(associate_command)


@app.callback()
def main() -> None:
    """rigsfm: metric calibration of hybrid (wide + narrow) stereo-rig networks.

    calibrate (board images -> rigs.yaml), run (image folders -> metric narrow poses, E_ji, F_ji), report /
    view / export (look at a result, hand it to other tools), pick (hand-picked correspondences), track
    (rig poses over time), demo (a rendered example with exact ground truth).
    """
