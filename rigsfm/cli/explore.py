"""``rigsfm explore``."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Annotated

import typer

from rigsfm.cli import _signals
from rigsfm.cli.common import configure_logging, console, fail_cleanly


@fail_cleanly
def explore_command(
    out: Annotated[Path, typer.Argument(metavar="OUT", help="a finished result (rigsfm run --out)",
                                        show_default=False)],
    frame: Annotated[str | None, typer.Option(
        "--frame", metavar="NAME",
        help="frame file name shown first [default: the first with narrow images of two or more rigs]",
        show_default=False)] = None,
    labels: Annotated[Path | None, typer.Option(
        "--labels", metavar="CSV", help="labels CSV to write and resume from [default: OUT/labels.csv]",
        show_default=False)] = None,
    check: Annotated[Path | None, typer.Option(
        "--check", metavar="CSV",
        help="print the share of this CSV's labelled pairs inside their band, and stop "
             "[default: serve the page]",
        show_default=False)] = None,
    heights: Annotated[str, typer.Option("--heights", metavar="LOW-HIGH",
                                         help="the band's segment, metres above the floor")] = "0-2.2",
    images: Annotated[Path | None, typer.Option(
        "--images", metavar="IMAGES", help="IMAGES [default: the run's, from summary.json]",
        show_default=False)] = None,
    port: Annotated[int, typer.Option("--port", min=0, max=65535, metavar="PORT",
                                      help="port on 127.0.0.1; 0 picks a free one")] = 0,
) -> None:
    """Check a result on people you can recognise: click one in a narrow view, see where they can be in the
    others; label correspondences (CSV)."""
    from rigsfm.explore.server import start_explorer
    from rigsfm.explore.session import ExploreOptions, check_labels, click_allowance_px, parse_heights

    configure_logging(False)
    options = ExploreOptions(frame=frame, labels=labels, images=images, heights=parse_heights(heights))
    if check is not None:
        result = check_labels(out, check, options)
        if not result.pairs:
            why = f" ({result.without_band} whose band leaves the image)" if result.without_band else ""
            console.print(f"{check}: no labelled pair of two rigs' narrow images with a band{why}")
            raise typer.Exit(1)
        for (i, j), (inside, total) in result.per_pair.items():
            console.print(f"  {i} - {j}: {inside} of {total} inside ({100 * inside / total:.1f} %)")
        rest = f"; {result.without_band} without a band in the other image" if result.without_band else ""
        noise = click_allowance_px(options.click_sigma_px)
        console.print(f"{result.inside} of {result.pairs} labelled pairs inside their 95 % band "
                      f"({100 * result.share:.1f} %), with {noise:.1f} px for the clicks' noise"  # type: ignore[operator]  # pairs: a share
                      f"{rest}")
        return
    server = start_explorer(out, options, port=port)
    session = server.session
    try:  # from the line that says Ctrl-C on: a Ctrl-C right after it stops the explorer, as pick's
        console.print(f"explorer for {out}, frame {session.frame} ({len(session.result.frames)} frames): open "
                      f"{server.url} (saves to {session.csv_path} on every change); Ctrl-C to stop")
        threading.Event().wait()
    except KeyboardInterrupt:  # Ctrl-C is how the explorer is meant to stop: done, not interrupted
        _signals.handled()
    finally:
        server.close()
    if not session.csv_path.exists():  # written at the first click, as pick's CSV
        console.print(f"stopped: no labels, so {session.csv_path} was not written")
        return
    console.print(f"stopped: {len(session.labels)} labels in {session.csv_path}")
