"""``associate_report_section(out)``: the persons of ``rigsfm associate``'s default folder (OUT/associate) as a
section of report.html: per frame the persons, the detections they hold, their views and position sigmas, and the
first frame's floor map and density grid."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np

from rigsfm.associate.output import MANIFEST
from rigsfm.core.workspace import Workspace, model_fingerprint

SHOWN_FRAMES = 20  # table rows; the frames after them are summed up in one line


def frame_counts(path: Path) -> tuple[dict, int, int]:
    """A frame's persons.json, the detections its persons hold and all its detections."""
    data = json.loads(path.read_text(encoding="utf-8"))
    assigned = sum(len(p["detections"]) for p in data["persons"])
    return data, assigned, assigned + len(data["unassigned"])


def lent_views(data: dict) -> list[str]:
    """The views of a frame's persons.json whose poses ``--poses-from`` lent: all of a frame the run was not given,
    some of a frame of the run that lacked their narrow images (an earlier version's file: all where it lent)."""
    if not data.get("poses_from"):
        return []
    return list(data.get("lent_views") or data.get("views") or [])


def poses_note(data: dict) -> str:
    """Whose narrow poses a frame's persons were found with, in words."""
    lent, views = lent_views(data), data.get("views") or []
    if not lent:
        return "its own"
    if len(lent) < len(views):
        return f"{len(lent)} of {len(views)} views lent by {data['poses_from']}, the others its own"
    return f"lent by {data['poses_from']}"


def _frame_row(path: Path) -> list[str]:
    data, assigned, total = frame_counts(path)
    persons = data["persons"]
    views = np.array([len(p["detections"]) for p in persons])
    sigma = np.array([np.sqrt(np.linalg.eigvalsh(np.asarray(p["covariance_m2"])[:2, :2]).max()) for p in persons])
    confident = sum(p["confidence"] >= 0.5 for p in persons)
    return [html.escape(str(data["frame"])), str(len(persons)), str(confident), str((views >= 3).sum()),
            f"{assigned} of {total}",
            f"{np.median(sigma) * 100:.1f}" if len(sigma) else "&ndash;",
            html.escape(poses_note(data))]


def _figure(path: Path, caption: str) -> str:
    if not path.is_file():
        return ""
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(caption)}" style="max-width:100%" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def _made_from_another_model(workspace: Workspace, fingerprint: str | None) -> bool:
    """Whether OUT/associate's manifest names a model other than OUT/sparse (an earlier version's names none)."""
    try:
        made_from = json.loads((workspace.associate / MANIFEST).read_text(encoding="utf-8")).get("model")
    except (OSError, ValueError, AttributeError):
        return False
    if not made_from or not workspace.sparse.is_dir():
        return False
    return made_from != (fingerprint if fingerprint is not None else model_fingerprint(workspace.sparse))


def associate_report_section(out: Path, fingerprint: str | None = None) -> str:
    """HTML (a <section>) of OUT/associate, or a short note where `rigsfm associate` has not written there.
    ``fingerprint``: OUT/sparse's ``model_fingerprint`` where the caller has it (the report hashes the model once)."""
    workspace = Workspace(Path(out))
    folder = workspace.associate
    frames = sorted(folder.glob("*/persons.json"))
    if not frames:
        return ('<section id="persons"><h2>Persons across the narrow views</h2><p>No association (run <code>rigsfm '
                "associate OUT DETECTIONS</code>).</p></section>")
    if _made_from_another_model(workspace, fingerprint):
        return ('<section id="persons"><h2>Persons across the narrow views</h2><p class="warn">The association in '
                f"{html.escape(str(folder))} was made from an earlier result of this folder (replaced by <code>rigsfm "
                "run --overwrite</code> since), so its persons are not shown: re-run <code>rigsfm associate "
                f"{html.escape(workspace.shell_root)} DETECTIONS --overwrite</code>.</p></section>")
    parts = ['<section id="persons">', "<h2>Persons across the narrow views</h2>",
             f"<p>{len(frames)} frame(s) associated by <code>rigsfm associate</code> in {html.escape(str(folder))}: "
             "each person's detections (at most one per view), its position in the world frame and its "
             "covariance (persons.csv / persons.json per frame). Confident: likelier one person than chance under "
             "the association's model (confidence &ge; 0.5: the model's odds, not a measured rate; with few views "
             "round a dense crowd most such persons can be wrong); sigma: the largest horizontal standard deviation "
             "of a position; poses: the "
             "run's own for the frame, or those of a frame of the run lent to a frame it was not given, or to the views "
             "of a frame whose narrow images it lacked (<code>--poses-from</code>: static rigs).</p>",
             "<table><thead><tr><th>frame</th><th>persons</th><th>confident</th><th>in &ge; 3 views</th>"
             "<th>detections assigned</th><th>sigma median (cm)</th><th>narrow poses</th></tr></thead><tbody>"]
    parts += ["<tr>" + "".join(f"<td>{cell}</td>" for cell in _frame_row(path)) + "</tr>"
              for path in frames[:SHOWN_FRAMES]]
    parts.append("</tbody></table>")
    if len(frames) > SHOWN_FRAMES:
        parts.append(f"<p>... and {len(frames) - SHOWN_FRAMES} more frames.</p>")
    first = frames[0].parent
    parts.append(_figure(first / "floor.png", f"{first.name}: persons' 95 % ellipses and the narrow footprints"))
    parts.append(_figure(first / "density.png", f"{first.name}: persons found per m2, those detected in two narrow "
                                                "views or more: in a dense crowd a fraction of those there, most "
                                                "heads hidden from all views but one (grey: seen by fewer than two "
                                                "narrow views)"))
    parts.append("</section>")
    return "\n".join(parts)
