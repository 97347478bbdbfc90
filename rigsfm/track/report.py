"""``track_report_section(out)``: an HTML fragment with the tracking verdicts and plots, for the report."""

from __future__ import annotations

import base64
import html
from pathlib import Path

from rigsfm.core.summary import Summary
from rigsfm.core.workspace import Workspace, model_fingerprint, read_json

VERDICT_STYLE = {"stable": "color:#2a7d2a", "shaking": "color:#c77700", "moved": "color:#c0392b;font-weight:bold"}


def track_report_section(out: Path, fingerprint: str | None = None) -> str:
    """HTML (a <section>) summarising OUT/track: per rig verdict, steps, jitter and the embedded PNG plot.
    ``fingerprint``: OUT/sparse's ``model_fingerprint`` where the caller has it (the report hashes the model once).

    Returns a short note when `rigsfm track` has not been run on this workspace.
    """
    paths = Workspace(Path(out)).track
    if not paths.poses_json.is_file():
        return '<section id="track"><h2>Pose tracking</h2><p>No tracking results (run <code>rigsfm track</code>).</p></section>'
    poses = read_json(paths.poses_json, "re-run `rigsfm track OUT NEW_IMAGES --overwrite`", keys=("thresholds", "rigs"))
    workspace = Workspace(Path(out))
    if fingerprint is None:
        fingerprint = model_fingerprint(workspace.sparse)
    if poses.get("reference", {}).get("fingerprint") != fingerprint:
        # as `rigsfm track` refuses to extend them: a `rigsfm run --overwrite` since replaced the model
        return ('<section id="track"><h2>Pose tracking</h2><p class="warn">The tracking results in '
                f"{html.escape(str(paths.root))} were made against an earlier result of this folder (replaced by "
                "<code>rigsfm run --overwrite</code> since), so their verdicts are not shown: re-run "
                f"<code>rigsfm track {html.escape(workspace.shell_root)} NEW_IMAGES --overwrite</code>.</p></section>")
    t = poses["thresholds"]
    summary = Summary.read(workspace.summary)
    parts = ['<section id="track">', "<h2>Pose tracking</h2>"]
    if summary is not None and summary.metric is False:  # as `rigsfm track` warns on the terminal
        parts.append('<p class="warn">Not metric: the run has no scale, so each &lsquo;mm&rsquo; below is a '
                     "thousandth of its arbitrary unit, the translation threshold included.</p>")
    parts += [(f"<p>Thresholds: {t['rotation_deg']:g}&nbsp;deg, {t['translation_mm']:g}&nbsp;mm (and significant at "
               f"chi&sup2; &gt; {t['significance_chi2']:g}); changes are measured from each rig's reference frame.</p>"),
              ("<table><thead><tr><th>rig</th><th>verdict</th><th>frames</th><th>registered</th><th>flagged</th>"
               "<th>steps (frame: deg, mm)</th><th>jitter RMS (deg, mm)</th></tr></thead><tbody>")]
    for name, rig in poses["rigs"].items():
        v = rig["verdict"]
        registered = sum(f["status"] == "registered" for f in rig["frames"])
        steps = "; ".join(f"{html.escape(s['frame'])}: {s['rotation_deg']:.3f}, {s['translation_mm']:.1f}"
                          for s in v["steps"]) or "&ndash;"
        jitter = ("&ndash;" if v["jitter_rotation_deg"] is None
                  else f"{v['jitter_rotation_deg']:.4f}, {v['jitter_translation_mm']:.1f}")
        parts.append(f"<tr><td>{html.escape(name)}</td><td style=\"{VERDICT_STYLE.get(v['verdict'], '')}\">"
                     f"{html.escape(v['verdict'])}</td><td>{len(rig['frames'])}</td><td>{registered}</td>"
                     f"<td>{v['flagged_frames']}</td><td>{steps}</td><td>{jitter}</td></tr>")
    parts.append("</tbody></table>")
    for name in poses["rigs"]:
        png = paths.plot(name)
        if png.is_file():
            data = base64.b64encode(png.read_bytes()).decode("ascii")
            parts.append(f'<figure><img alt="pose changes of {html.escape(name)}" src="data:image/png;base64,{data}">'
                         f"<figcaption>{html.escape(name)}: rotation and translation change per frame</figcaption></figure>")
    parts.append("</section>")
    return "\n".join(parts)
