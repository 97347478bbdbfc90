"""Size of report.html against the number of rigs: the epipolar-check figures dominate it.

    python benchmarks/report_size.py --rigs 8 16 [--image-scale 0.5] [--work DIR] [--old-code PATH]

Renders a full circle of N rigs (``render_dataset``, seed 1), runs ``rigsfm run`` once per scene (kept in
``--work`` and reused), then writes report.html with this checkout's code, and with ``--old-code`` (a checkout
put first on PYTHONPATH, e.g. one at an older commit) into a copy for comparison. Prints one JSON line per
scene: the report's size, the number of narrow pairs, of figures and the bytes of their images. The figures are
resized to a fixed panel width, so their size depends little on the image scale (checked at 3 rigs: see the
README of benchmarks).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path


def workspace(work: Path, rigs: int, image_scale: float) -> Path:
    from rigsfm.run.pipeline import run
    from rigsfm.synth.dataset import render_dataset
    from rigsfm.synth.scene import SceneOptions

    root = work / f"rigs{rigs}_scale{image_scale:g}"
    out = root / "out"
    if not (out / "summary.json").is_file():
        dataset = render_dataset(root / "scene", SceneOptions(num_rigs=rigs, image_scale=image_scale, seed=1),
                                 overwrite=True)
        run(dataset.images, dataset.rigs, out, dataset.scale)
    return out


def measure(report: Path) -> dict:
    text = report.read_text(encoding="utf-8")
    images = re.findall(r'src="data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)"', text)
    return {"report_bytes": report.stat().st_size, "figures": len(images),
            "figure_bytes": sum(len(data) for _, data in images),
            "formats": sorted({kind for kind, _ in images})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rigs", type=int, nargs="+", default=[8, 16])
    parser.add_argument("--image-scale", type=float, default=0.5)
    parser.add_argument("--work", type=Path, default=Path("/tmp/rigsfm-report-size"))
    parser.add_argument("--old-code", type=Path, default=None)
    args = parser.parse_args()

    from rigsfm.inspect.report.write import write_report

    for rigs in args.rigs:
        out = workspace(args.work, rigs, args.image_scale)
        narrow = json.loads((out / "narrow_poses.json").read_text())
        row = {"benchmark": "report_size", "rigs": rigs, "image_scale": args.image_scale,
               "narrow_pairs": len(narrow["pairs"])}
        start = time.perf_counter()
        row["new"] = measure(write_report(out))
        row["new"]["seconds"] = round(time.perf_counter() - start, 1)
        if args.old_code is not None:
            old = out.parent / "out_old_report"
            shutil.rmtree(old, ignore_errors=True)
            shutil.copytree(out, old)
            env = {**os.environ, "PYTHONPATH": str(args.old_code)}
            subprocess.run([sys.executable, "-m", "rigsfm", "report", str(old)], check=True, env=env,
                           capture_output=True, cwd=args.old_code)  # -m puts the working folder first on the path
            row["old"] = measure(old / "report.html")
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
