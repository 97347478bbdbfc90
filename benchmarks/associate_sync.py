"""Frame offsets from a user's head detections: does `rigsfm associate` tell a rig whose frames are late?

    python benchmarks/associate_sync.py RECORDING RUN --cases "none;rig03=1;rig02=-1,rig06=1" [--seeds 1]
        [--frames 4] [--search 2] [--json results.json]
    python benchmarks/associate_sync.py RECORDING RUN --library WORK --cases "none@2;rig01=1,rig04=-2@3"

``--library``: rigsfm.associate.sync's own check on associate_frames' chain of each case (``case@seed``: that
detection seed alone), with the verdict the counts under the carried corrections alone would give (the check before
``confirmed_counts``) beside it, and the CPU of the recount.

RECORDING: a synchronised recording rendered with persons (``python -m rigsfm.synth ... --frames-per-rig 9``);
RUN: ``rigsfm run`` on its frame 0 alone (its narrow poses are lent to every other frame, ``--poses-from``).
A case's offsets make an unsynchronised recording out of the synchronised one: rig r's frame k is the recording's
frame k + offset_r (images and heads; the crowd walks, the rigs stand), which is what ``--frame-offsets rig03=1``
renders, the calibrated frame 0 aside. Detections per recording frame as benchmarks/associate.py makes them (the
issue's model: true visible heads + 1.5 px, 10 % missed, 5 % false; seed + 1000 q for recording frame q).

Per case the frames are associated as `rigsfm associate --poses-from` does (the first self-calibrates, the rest
carry). At each tested frame k, for every rig r and shift s in -search..search, frame k is associated again from the
same carried state with r's detections (and image) taken from r's own frame k + s, the others' unchanged: every
shift is one whole association with r in it, so the tested view takes part in choosing the persons at every shift
alike (like with like). Scores per (r, s), summed over the tested frames: r's detections in confident persons
(three or more views, positive score), and r's share of them. The rigs' share at s = 0 is step one's question:
does a late rig stand out without any search.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

from rigsfm.associate import AssociateOptions, from_arrays, load_run, sync
from rigsfm.associate.evaluate import make_detections, visible_heads
from rigsfm.associate.pipeline import frame_views, with_stand_ins
from rigsfm.associate.solve import associate_views
from rigsfm.core.names import ImageName


def parse_case(text: str) -> dict[str, int]:
    if text in ("", "none", "all0"):
        return {}
    return {rig: int(value) for rig, value in (item.split("=") for item in text.split(","))}


def rig_of(camera: str) -> str:
    return camera.split("/")[0]


def recording_model(recording: Path, run: Path, frames: int):
    """The run's model with its frame 0's poses lent to every frame of RECORDING, the bands between any two frames'
    images of two cameras those of the cameras (static rigs), the images read from RECORDING."""
    model = load_run(run)
    reference = sorted({ImageName.parse(n).frame for n in model.images})[0]
    names = [n for q in range(frames) for n in visible_heads(recording, f"frame{q:04d}")]
    model = with_stand_ins(model, names, reference)
    by_camera = {ImageName.parse(n).camera: n for n in model.images if n not in model.stand_ins}
    bands = dict(model.bands)
    for a in model.images:
        for b in model.images:
            ca, cb = ImageName.parse(a).camera, ImageName.parse(b).camera
            if ca != cb and (by_camera[ca], by_camera[cb]) in model.bands:
                bands[(a, b)] = model.bands[(by_camera[ca], by_camera[cb])]
    return dataclasses.replace(model, bands=bands, images_root=recording / "images"), reference


def name_at(model, camera: str, q: int) -> str:
    return f"{camera}/frame{q:04d}.png"


def confident_counts(result, options: AssociateOptions) -> dict[str, tuple[int, int, float]]:
    """Per view: its detections in confident persons, in any person, and the confident persons' summed score."""
    members = result.members
    confident = (np.sum(members >= 0, axis=1) >= 3) & (result.scores > options.self_calibration_min_score)
    out = {}
    for v, name in enumerate(result.views):
        mine = members[:, v] >= 0
        out[name] = (int(np.sum(confident & mine)), int(np.sum(mine)),
                     float(np.sum(result.scores[confident & mine])))
    return out


def run_case(model, dets, offsets: dict[str, int], cameras: list[str], first: int, tested: list[int],
             search: int, options: AssociateOptions, templates: dict, reset: bool = False) -> dict:
    def view(camera: str, q: int):
        return copy.copy(templates[name_at(model, camera, q)])

    def given(camera: str, k: int) -> int:
        return k + offsets.get(rig_of(camera), 0)

    wall, cpu = time.perf_counter(), time.process_time()
    views = [view(c, given(c, first)) for c in cameras]
    earlier = associate_views(views, options, carried=False, earlier=None)
    carried = {c: v for c, v in zip(cameras, views)}
    first_cpu = time.process_time() - cpu
    table: dict[str, dict[int, list]] = {c: {s: [] for s in range(-search, search + 1)} for c in cameras}
    detections: dict[str, dict[int, list]] = {c: {s: [] for s in range(-search, search + 1)} for c in cameras}
    def associate(k: int, carried: dict, earlier, shifted: str | None = None, s: int = 0):
        trial = [view(c, given(c, k) + (s if c == shifted else 0)) for c in cameras]
        for v, c in zip(trial, cameras):
            if not (reset and c == shifted):
                v.carry(carried[c])
        return trial, associate_views(trial, options, carried=True, earlier=earlier)

    for k in range(first + 1, tested[-1] + 1):
        base_views, base = associate(k, carried, earlier)
        if k in tested:
            counts = confident_counts(base, options)
            for c, v in zip(cameras, base_views if not reset else []):
                table[c][0].append(counts[v.name])
                detections[c][0].append(len(v.xy))
            for c in cameras:
                for s in range(-search, search + 1):
                    if s == 0 and not reset:
                        continue
                    trial, result = associate(k, carried, earlier, c, s)
                    name = trial[cameras.index(c)].name
                    table[c][s].append(confident_counts(result, options)[name])
                    detections[c][s].append(len(trial[cameras.index(c)].xy))
        carried = {c: v for c, v in zip(cameras, base_views)}
        earlier = base
    return {"table": table, "detections": detections, "first_cpu_s": first_cpu,
            "cpu_s": time.process_time() - cpu, "wall_s": time.perf_counter() - wall}


def summarise(case: dict, cameras: list[str], search: int) -> list[dict]:
    rows = []
    for c in cameras:
        conf = {s: sum(t[0] for t in case["table"][c][s]) for s in range(-search, search + 1)}
        per_frame = {s: [t[0] for t in case["table"][c][s]] for s in range(-search, search + 1)}
        n = {s: sum(case["detections"][c][s]) for s in range(-search, search + 1)}
        rows.append({"camera": c, "confident": conf, "per_frame": per_frame, "detections": n,
                     "share0": conf[0] / max(n[0], 1)})
    return rows


def library_case(recording: Path, run: Path, offsets: dict[str, int], frames: int, seed: int, work: Path,
                 options: AssociateOptions, recount: str = "self") -> dict:
    """``rigsfm associate``'s own check (rigsfm.associate.sync) on the case's recording of ``frames`` frames: rig r's
    frame k is the recording's frame k + offset_r + ``lead`` (so that every frame exists), its images linked into
    ``work`` (the appearance cue reads them there), the detections made from the recording's frames."""
    from rigsfm.associate.pipeline import associate_frames
    from rigsfm.associate.sync import check_frame_offsets

    lead = max([0] + [-o for o in offsets.values()])
    model = load_run(run)
    reference = sorted({ImageName.parse(n).frame for n in model.images})[0]
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    cameras = sorted({ImageName.parse(n).camera for n in model.images})
    points = {}
    for k in range(frames):
        for camera in cameras:
            q = k + offsets.get(rig_of(camera), 0) + lead
            source = f"{camera}/frame{q:04d}.png"
            heads = {n: v for n, v in visible_heads(recording, f"frame{q:04d}").items() if n == source}
            truth = make_detections(heads, {source: sizes[name_at(model, camera, 0)]}, sigma_px=1.5, missed=0.1,
                                    false=0.05, seed=seed + 1000 * q)
            name = f"{camera}/frame{k:04d}.png"
            points[name] = truth.points[source]
            link = work / "images" / name
            link.parent.mkdir(parents=True, exist_ok=True)
            if link.is_symlink():
                link.unlink()
            link.symlink_to((recording / "images" / source).resolve())
    dets = from_arrays(points)
    model = with_stand_ins(model, [n for n in dets.images if n not in model.images], reference)
    model = dataclasses.replace(model, images_root=work / "images")
    cpu = time.process_time()
    chain = associate_frames(model, dets, options)
    chain_cpu = time.process_time() - cpu
    calls: list[float] = []
    counting = sync.shift_counts

    def timed(*args, **kwargs):
        start = time.process_time()
        try:
            return counting(*args, **kwargs)
        finally:
            calls.append(time.process_time() - start)

    confirming = sync.confirmed_counts
    sync.shift_counts = timed  # the recount's own CPU (the second call, where a rig is doubted)
    if recount == "own":  # the doubted rig's correction not carried, the others' carried (cheap: no self-calibration)
        sync.confirmed_counts = functools.partial(confirming, own_pose=True)
    try:
        check = check_frame_offsets(model, dets, chain, options, "check", correct=sync.Correction.CONFIRM)
    finally:
        sync.shift_counts, sync.confirmed_counts = counting, confirming
    record = check.to_dict()
    return {**record, "carried_only": carried_only(record), "chain_cpu_s": chain_cpu,
            "check_cpu_s": time.process_time() - cpu - chain_cpu, "recount_cpu_s": sum(calls[1:])}


def carried_only(record: dict) -> dict:
    """The verdict of the counts under the carried corrections alone (the check before ``confirmed_counts``): per
    rig its offset and z, and the median lead."""
    counts = {}
    for rig, t in record["rigs"].items():
        got = t.get("carried_confident_detections") or t["confident_detections"]
        counts[rig] = {int(s): c for s, c in got.items()}
    out = {r: {"offset": t.offset, "z": round(t.z, 2)} for r, t in sync.timings(counts).items()}
    leads = []
    for c in counts.values():
        first, second = sorted(c.values(), reverse=True)[:2]
        leads.append((first - second) / max(first + second, 1) ** 0.5)
    return {"rigs": out, "named": {r: t["offset"] for r, t in out.items() if t["offset"]},
            "median_lead": round(float(np.median(leads)), 2)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--cases", default="none;rig03=1")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--recording-frames", type=int, default=9)
    parser.add_argument("--frames", type=int, default=4, help="tested frames per case")
    parser.add_argument("--search", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--reset", action="store_true",
                        help="the tested rig's view does not carry its own shift (every shift, 0 included): a late "
                             "rig's self-calibration was made on its late frames")
    parser.add_argument("--recount", choices=("self", "own"), default="self",
                        help="--library: the doubted rigs counted again each association correcting itself (the "
                             "check's), or carrying the others' corrections and not the rig's own")
    parser.add_argument("--library", type=Path, default=None, metavar="WORK",
                        help="run rigsfm.associate.sync's check instead (the case's images linked under WORK)")
    args = parser.parse_args(argv)
    options = AssociateOptions(pixel_sigma=1.5)
    if args.library is not None:
        records = []
        runs = [(seed, text) for seed in range(args.seeds) for text in args.cases.split(";") if "@" not in text]
        runs += [(int(text.split("@")[1]), text.split("@")[0]) for text in args.cases.split(";") if "@" in text]
        for seed, text in runs:
            offsets = parse_case(text)
            span = args.recording_frames - max([0] + list(offsets.values())) + min([0] + list(offsets.values()))
            record = library_case(args.recording, args.run, offsets, span, seed, args.library / f"s{seed}_{text}",
                                  options, args.recount)
            records.append({"seed": seed, "case": text, **record})
            print(json.dumps(records[-1]), flush=True)
        if args.json:
            args.json.write_text(json.dumps(records, indent=1))
        return 0
    model, _ = recording_model(args.recording, args.run, args.recording_frames)
    cameras = sorted({ImageName.parse(n).camera for n in model.images})
    sizes = {n: (im.camera.width, im.camera.height) for n, im in model.images.items()}
    out = []
    for seed in range(args.seeds):
        points = {}
        for q in range(args.recording_frames):
            heads = {n: v for n, v in visible_heads(args.recording, f"frame{q:04d}").items() if n in sizes}
            points.update(make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05,
                                          seed=seed + 1000 * q).points)
        dets = from_arrays(points)
        templates = {}
        for q in range(args.recording_frames):
            names = [name_at(model, c, q) for c in cameras]
            for v in frame_views(model, dets, f"frame{q:04d}.png", names):
                templates[v.name] = v
        for text in args.cases.split(";"):
            offsets = parse_case(text)
            lo = max([0] + [args.search - o for o in offsets.values()] + [args.search])
            hi = min([args.recording_frames - 1 - args.search - o for o in offsets.values()]
                     + [args.recording_frames - 1 - args.search])
            tested = list(range(lo, hi + 1))[: args.frames]
            first = tested[0] - 1
            if first + min([0] + list(offsets.values())) < 0:
                raise SystemExit(f"case {text}: no frame before the tested ones")
            case = run_case(model, dets, offsets, cameras, first, tested, args.search, options, templates,
                            args.reset)
            rows = summarise(case, cameras, args.search)
            record = {"seed": seed, "case": text, "offsets": offsets, "first": first, "tested": tested,
                      "first_cpu_s": case["first_cpu_s"], "cpu_s": case["cpu_s"], "wall_s": case["wall_s"],
                      "rows": rows}
            out.append(record)
            print(f"seed {seed} case {text or 'none'} tested {tested} ({case['cpu_s']:.0f} s CPU, first "
                  f"{case['first_cpu_s']:.0f} s)", flush=True)
            for r in rows:
                conf = " ".join(f"{s:+d}:{r['confident'][s]:4d}" for s in sorted(r["confident"]))
                print(f"  {r['camera']:14s} share0 {r['share0']:.2f}  {conf}  per frame at 0 {r['per_frame'][0]}",
                      flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
