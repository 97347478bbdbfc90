"""Positive controls of ``CALIBRATION CONTRADICTED``: networks of ``benchmarks/networks.py`` run by default with one
rig's focal length in rigs.yaml made wrong by a known share, and whether the warning fires.

    python benchmarks/contradicted.py WORK --networks flat4_135_s0 ... [--rig rig01] [--sensor narrow]
        [--percent 1 0.5] [--out FILE]

Each network's render is ``networks.py``'s (cached under ``WORK/<name>/scene``, rendered there if missing); its
rigs.yaml (the realistic calibration error and its sigmas) is copied with ``fx`` and ``fy`` of ``--rig``'s
``--sensor`` multiplied by ``1 + percent / 100``, sigmas unchanged, and run as ``networks.run_one`` runs the default
(``WORK/<name>/contra_<sensor>_<percent>``). Per run: the decisions' record (``networks.decisions_record``: the
network's chi-square, dof, limits, rigs refined, whether it warned) and the scores against the exact truth.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from types import SimpleNamespace

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from benchmarks.networks import dataset, networks, run_one  # noqa: E402
from rigsfm.core.io import write_json_atomic  # noqa: E402

logger = logging.getLogger("benchmarks.contradicted")


def wrong_rigs(rigs: Path, out: Path, rig: str, sensor: str, percent: float) -> Path:
    """``rigs`` with ``rig``'s ``sensor`` focal lengths (fx, fy) ``percent`` % too high, written to ``out``."""
    spec = yaml.safe_load(rigs.read_text(encoding="utf-8"))
    entry = next(r for r in spec["rigs"] if r["name"] == rig)
    params = entry["sensors"][sensor]["params"]
    params[0] *= 1 + percent / 100
    params[1] *= 1 + percent / 100
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(spec, sort_keys=False), encoding="utf-8")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("work", type=Path)
    parser.add_argument("--networks", nargs="+", required=True, choices=sorted(networks()))
    parser.add_argument("--rig", default="rig01")
    parser.add_argument("--sensor", default="narrow", choices=("wide", "narrow"))
    parser.add_argument("--percent", nargs="+", type=float, default=[1.0, 0.5])
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    for noisy in ("rigsfm", "pycolmap"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    results = []
    for name in args.networks:
        network = networks()[name]
        data = dataset(network, args.work)
        for percent in args.percent:
            folder = args.work / name / f"contra_{args.sensor}_{percent:g}"
            rigs = wrong_rigs(data.rigs, folder / "rigs.yaml", args.rig, args.sensor, percent)
            row, _ = run_one(network, SimpleNamespace(images=data.images, rigs=rigs, scale=data.scale,
                                                      ground_truth=data.ground_truth), folder / "run", False, None)
            d = row["decisions"]
            logger.info("%s %s %s +%g %%: chi-square %s on %s dof (limits %s, %s), refined %s, warned %s", name,
                        args.rig, args.sensor, percent, d["network_chi2"], d["network_dof"], d["limit_hold"],
                        d["limit_contradicted"], d["refined"], d["contradicted"])
            results.append({"network": name, "rig": args.rig, "sensor": args.sensor, "percent": percent,
                            "default": row})
            write_json_atomic(args.out or args.work / f"contradicted_{args.sensor}.json", {"results": results},
                              overwrite=True)


if __name__ == "__main__":
    main()
