"""Time to validate a large rigs.yaml: parse (YAML, duplicate keys refused) and check every rig.

    python benchmarks/validation.py [--rigs 100 1000 3000] [--repeat 5]

Writes, under a temporary folder, one rigs.yaml per size as ``rigsfm calibrate`` writes it (OPENCV wide and narrow
cameras, every sigma and the 6x6 covariance: ~0.94 KB a rig), then times :func:`rigsfm.core.rig.load_rigs` on it
(CPU seconds of this process, the best of ``--repeat``), split into the parse (:func:`rigsfm.core.io.parse_yaml`)
and the rest (the rig checks). Prints one JSON line per size; linear validation keeps the time per rig constant.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path


def rigs_file(folder: Path, count: int) -> Path:
    import numpy as np
    import pycolmap

    from rigsfm.core.rig import RigCalibration, RigSigmas, write_rigs

    wide = pycolmap.Camera(model="OPENCV", width=1624, height=1234,
                           params=[900.0, 900.0, 812.0, 617.0, -0.1, 0.01, 0.0, 0.0])
    narrow = pycolmap.Camera(model="OPENCV", width=1624, height=1234,
                             params=[3600.0, 3600.0, 812.0, 617.0, 0.01, 0.0, 0.0, 0.0])
    covariance = np.diag([np.radians(0.02) ** 2] * 3 + [1e-4 ** 2] * 3)
    sigmas = RigSigmas(wide=np.array([0.5, 0.5, 0.6, 0.6, 1e-3, 1e-4, 1e-5, 1e-5]),
                       narrow=np.array([1.5, 1.5, 0.8, 0.9, 1e-3, 1e-4, 1e-5, 1e-5]),
                       rotation_deg=np.array([0.02, 0.03, 0.01]), translation_m=np.array([1e-4, 1e-4, 3e-4]),
                       covariance=covariance)
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(), [-0.06, 0.0, 0.001])
    rigs = [RigCalibration(f"rig{i:05d}", wide, narrow, pose, sigmas=sigmas) for i in range(count)]
    return write_rigs(folder / f"rigs{count}.yaml", rigs, overwrite=True)


def cpu_seconds(function, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.process_time()
        function()
        best = min(best, time.process_time() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rigs", type=int, nargs="+", default=[100, 1000, 3000])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()

    from rigsfm.core.io import parse_yaml
    from rigsfm.core.rig import load_rigs

    with tempfile.TemporaryDirectory(prefix="rigsfm-validation-") as folder:
        for count in args.rigs:
            path = rigs_file(Path(folder), count)
            text = path.read_text()
            load = cpu_seconds(lambda: load_rigs(path), args.repeat)  # noqa: B023  (called at once)
            parse = cpu_seconds(lambda: parse_yaml(text), args.repeat)  # noqa: B023
            print(json.dumps({"rigs": count, "bytes": len(text.encode()), "load_rigs_s": round(load, 3),
                              "parse_s": round(parse, 3), "checks_s": round(load - parse, 3),
                              "ms_per_rig": round(1000 * load / count, 3)}), flush=True)


if __name__ == "__main__":
    main()
