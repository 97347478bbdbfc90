"""The ``rigsfm`` command: a thin typer shell over the library, one module per verb.

Only this package imports typer. It imports nothing heavy at start (each command imports its library when
it runs), so ``rigsfm --help`` answers at once.
"""

from __future__ import annotations

from rigsfm.cli import _signals

if _signals.is_the_command():
    _signals.install()  # before anything else: a signal at any moment gives rigsfm's one line

import typer

from rigsfm.cli.associate import associate_command
from rigsfm.cli.calibrate import calibrate_command
from rigsfm.cli.explore import explore_command
from rigsfm.cli.inspect import export_command, report_command, view_command
from rigsfm.cli.pick import pick_command
from rigsfm.cli.run import demo_command, run_command
from rigsfm.cli.track import track_command


class Command(typer.core.TyperCommand):
    """Usage lines name arguments as their help does (``IMAGES``, not ``{IMAGES}``)."""

    def collect_usage_pieces(self, ctx) -> list[str]:
        return [piece[1:-1] if piece.startswith("{") and piece.endswith("}") else piece
                for piece in super().collect_usage_pieces(ctx)]


# Click's plain help (not Rich's boxes): at 80 columns Rich's table cut option names and wrapped the
# descriptions at ~15 characters.
app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None,
                  context_settings={"help_option_names": ["-h", "--help"]})

app.command("calibrate", cls=Command)(calibrate_command)
app.command("run", cls=Command)(run_command)
app.command("report", cls=Command)(report_command)
app.command("view", cls=Command)(view_command)
app.command("export", cls=Command)(export_command)
app.command("pick", cls=Command)(pick_command)
app.command("explore", cls=Command)(explore_command)
app.command("associate", cls=Command)(associate_command)
app.command("track", cls=Command)(track_command)
app.command("demo", cls=Command)(demo_command)


@app.callback()
def main() -> None:
    """rigsfm: metric calibration of hybrid (wide + narrow) stereo-rig networks.

    calibrate (board images -> rigs.yaml), run (image folders -> metric narrow poses, E_ji, F_ji), report /
    view / export (look at a result, hand it to other tools), pick (hand-picked correspondences), explore (check
    a result on people you recognise, label them), associate (detections -> the same person in every narrow
    view, positions on the floor), track (rig poses over time), demo (a rendered example with exact ground truth).
    """
