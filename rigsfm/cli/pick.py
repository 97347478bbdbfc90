"""``rigsfm pick``."""

from __future__ import annotations

import shlex
import threading
from pathlib import Path
from typing import Annotated

import typer

from rigsfm.cli import _signals
from rigsfm.cli.common import console, fail_cleanly


@fail_cleanly
def pick_command(
    image_a: Annotated[Path, typer.Argument(metavar="IMAGE_A", help="first wide image, IMAGES/<rig>/wide/<file>", show_default=False)],
    image_b: Annotated[Path, typer.Argument(metavar="IMAGE_B", help="second wide image", show_default=False)],
    out: Annotated[Path, typer.Option("--out", help="CSV to write (and to resume from if it exists)",
                                      show_default=False)],
    rigs: Annotated[Path | None, typer.Option(
        "--rigs", help="rigs.yaml: epipolar curves through the calibrated lenses  [default: straight lines from the "
                       "pixels]", show_default=False)] = None,
    port: Annotated[int, typer.Option("--port", min=0, max=65535, metavar="PORT", help="port on 127.0.0.1; 0 picks a free one")] = 0,
    flag_px: Annotated[float, typer.Option("--flag-px", min=0.0, metavar="PX",
                                           help="flag pairs farther than this from their epipolar line (px)")] = 4.0,
) -> None:
    """Pick correspondences between two wide images in the browser (for run --manual-matches)."""
    from rigsfm.pick.server import start_picker

    server = start_picker(image_a, image_b, out, rigs, port, flag_px)
    try:
        if rigs is None:  # a wide lens bends its lines: true pairs far from the image centre are flagged
            console.print(f"without --rigs the epipolar lines ignore the lenses' distortion, so pairs near the edges "
                          f"may be flagged (> {flag_px:g} px) though right; pass --rigs rigs.yaml for curves")
        console.print(f"picker for {server.session.images[0].name} <-> {server.session.images[1].name}: "
                      f"open {server.url} (saves to {out} on every change); Ctrl-C to stop")
        threading.Event().wait()
    except KeyboardInterrupt:  # Ctrl-C is how the picker is meant to stop: done, not interrupted
        _signals.handled()
    finally:
        server.close()
    session = server.session
    if session.unsaved is not None:  # the last save failed: say so instead of "nothing finished was lost"
        from rigsfm.core.errors import WorkspaceError

        where = (f"they are kept in {session.rescue}: copy it to where the CSV should be"
                 if session.rescue is not None else "nothing could keep them")
        raise WorkspaceError(f"the last save of {len(session.unsaved)} pairs of {session.images[0].name} <-> "
                             f"{session.images[1].name} failed ({session.save_error}); {where}") from None
    if not out.exists():  # the CSV is written at the first change: "0 pairs in it" named a file that is not there
        console.print(f"stopped: no pairs picked, so {out} was not written")
        return
    console.print(f"stopped: {len(session.pairs)} pairs in {out} (for `rigsfm run ... --manual-matches {shlex.quote(str(out))}`)")
