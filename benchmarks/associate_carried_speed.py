"""CPU of a carried frame (its association and its files) for two versions of ``rigsfm.associate`` in one process.

    python benchmarks/associate_carried_speed.py capture DATASET OUT DIR [--seeds 2] [--carried 3]
    python benchmarks/associate_carried_speed.py compare OUT DIR --old-code CHECKOUT [--rounds 8]

``capture``: frame 0 and ``--carried`` carried frames per seed, as benchmarks/associate_speed.py makes them (DATASET,
OUT: a rendered crowd and ``rigsfm run`` on it), each carried frame's inputs (views, options, the frame before's
persons, detections) pickled into DIR once, with this checkout's code. ``compare``: the captured frames associated
(``associate_views``, carried) and written (``write_results``, all frames in one call, as the command writes them)
by CHECKOUT's ``rigsfm/associate`` (copied under another package name; the rest of ``rigsfm`` is this checkout's)
and by this checkout's, alternating, ``--rounds`` times; prints each round's CPU per frame, the min and median per
version, and whether every frame's persons (members, points, covariances, scores, the shifts used and left for the
next frame) and its five files' bytes are the same in both (md5). The machine's load moves a run by more than a
small change: one process, alternating, min and median.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import io
import pickle
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OLD = "old_rigsfm_associate"  # the package name CHECKOUT's rigsfm/associate is copied under


class _Renamed(pickle.Unpickler):
    """Unpickles the captured frames into the classes of another copy of ``rigsfm.associate``."""

    def __init__(self, data: bytes, package: str):
        super().__init__(io.BytesIO(data))
        self.package = package

    def find_class(self, module: str, name: str):
        if module.startswith("rigsfm.associate"):
            module = self.package + module[len("rigsfm.associate"):]
        return super().find_class(module, name)


def capture(dataset: Path, out: Path, folder: Path, seeds: int, carried: int) -> None:
    from benchmarks.associate_speed import static_frames
    from rigsfm.associate import AssociateOptions
    from rigsfm.associate.solve import associate_views

    folder.mkdir(parents=True, exist_ok=True)
    options = AssociateOptions()
    for seed in range(seeds):
        earlier = None
        for k, _, views, detections in static_frames(dataset, out, seed, carried):
            if k > 0:
                (folder / f"seed{seed}_frame{k}.pkl").write_bytes(pickle.dumps((views, options, earlier, detections)))
            cpu = time.process_time()
            earlier = associate_views(views, options, carried=k > 0, earlier=earlier)
            print(f"seed {seed} frame {k}: {len(earlier)} persons, {time.process_time() - cpu:.2f} s CPU", flush=True)


def _result_md5(result, views) -> str:
    digest = hashlib.md5()
    for array in (result.members, result.points, result.covariances, result.scores):
        digest.update(np.ascontiguousarray(array).tobytes())
    for name in sorted(result.shift_px):
        digest.update(np.asarray(result.shift_px[name]).tobytes())
    for view in views:  # what the next frame carries
        digest.update(np.asarray(view.shift_px).tobytes())
        digest.update(repr((view.sigma_pose_px, view.band_sigma_px, view.shift_sigma_px, view.head_px)).encode())
    return digest.hexdigest()


def _folder_md5(folder: Path) -> str:
    digest = hashlib.md5()
    for path in sorted(folder.rglob("*")):
        if path.is_file():
            digest.update(path.relative_to(folder).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()


def _old_package(checkout: Path, into: Path) -> None:
    """CHECKOUT's rigsfm/associate copied into ``into`` as package ``OLD``, its own imports renamed."""
    target = into / OLD
    shutil.copytree(checkout / "rigsfm" / "associate", target, ignore=shutil.ignore_patterns("__pycache__"))
    for path in target.glob("*.py"):
        path.write_text(path.read_text().replace("rigsfm.associate", OLD))
    sys.path.insert(0, str(into))


def compare(out: Path, folder: Path, old_code: Path, rounds: int) -> int:
    from rigsfm.associate import load_run

    model = load_run(out)
    work = Path(tempfile.mkdtemp(prefix="carried-speed-"))
    try:
        _old_package(old_code, work)
        packages = {"old": OLD, "new": "rigsfm.associate"}
        modules = {v: tuple(importlib.import_module(f"{p}.{m}") for m in ("solve", "output", "pipeline"))
                   for v, p in packages.items()}
        paths = sorted(folder.glob("seed*_frame*.pkl"))
        blobs = [p.read_bytes() for p in paths]
        cpu: dict[str, dict[str, list[float]]] = {v: {"association": [], "files": []} for v in packages}
        hashes: dict[str, dict[str, set[str]]] = {v: {} for v in packages}
        for r in range(rounds):
            for version in (list(packages) if r % 2 == 0 else list(packages)[::-1]):
                solve, output, pipeline = modules[version]
                association, frames = 0.0, []
                for k, (path, blob) in enumerate(zip(paths, blobs)):
                    views, options, earlier, detections = _Renamed(blob, packages[version]).load()
                    start = time.process_time()
                    result = solve.associate_views(views, options, carried=True, earlier=earlier)
                    association += time.process_time() - start
                    frames.append(pipeline.FramePersons(f"frame{k:04d}.png", result, detections, views))
                    hashes[version].setdefault(path.stem, set()).add(_result_md5(result, views))
                dest = work / f"{version}{r}"
                start = time.process_time()
                output.write_results(dest, model, frames, options)
                files = time.process_time() - start
                for k, path in enumerate(paths):
                    hashes[version].setdefault(path.stem + " files", set()).add(_folder_md5(dest / f"frame{k:04d}"))
                shutil.rmtree(dest)
                cpu[version]["association"].append(association / len(paths))
                cpu[version]["files"].append(files / len(paths))
                print(f"round {r} {version}: association {association / len(paths):.4f} s, files "
                      f"{files / len(paths):.4f} s CPU per frame", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    for version, parts in cpu.items():
        total = [a + f for a, f in zip(parts["association"], parts["files"])]
        print(version, "; ".join(f"{name} min {min(v):.4f} median {statistics.median(v):.4f}"
                                 for name, v in (*parts.items(), ("total", total))))
    same = True
    for key in sorted(hashes["new"]):
        found = hashes["old"].get(key, set()) | hashes["new"][key]
        same &= len(found) == 1
        print(key, "the same" if len(found) == 1 else f"DIFFERENT {sorted(found)}")
    return 0 if same else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    take = commands.add_parser("capture")
    take.add_argument("dataset", type=Path)
    take.add_argument("out", type=Path)
    take.add_argument("folder", type=Path)
    take.add_argument("--seeds", type=int, default=2)
    take.add_argument("--carried", type=int, default=3)
    both = commands.add_parser("compare")
    both.add_argument("out", type=Path)
    both.add_argument("folder", type=Path)
    both.add_argument("--old-code", type=Path, required=True, help="a checkout of the code to compare against")
    both.add_argument("--rounds", type=int, default=8)
    args = parser.parse_args(argv)
    if args.command == "capture":
        capture(args.dataset, args.out, args.folder, args.seeds, args.carried)
        return 0
    return compare(args.out, args.folder, args.old_code, args.rounds)


if __name__ == "__main__":
    sys.exit(main())
