"""A crowd of 3D persons: calibrate the network, then find the same person in every narrow view.

Renders hybrid rigs on an arc round a dense crowd (4 persons per m2, heads at 1.5-1.9 m, bodies occluding each
other), runs rigsfm with its defaults (where the narrow views share heads, the heads become observations of the
narrow cameras), stands in for your head detector with the true visible heads (1.5 px noise, 10 % missed, 5 %
false), groups them into persons (`rigsfm associate`'s library call), joins each person's detections back to the
CSV rows, writes the report, and scores both steps against the exact ground truth.

    python workflows/crowd.py OUT [--num-rigs 8] [--arc-deg 360] [--image-scale 0.5]

With your own images: `rigsfm run IMAGES --rigs rigs.yaml --scale scale.yaml --out OUT` (scale.yaml with a known
length on the floor, so the run finds the floor), your detector's heads as `image,x,y` rows in heads.csv, then
`rigsfm associate OUT heads.csv` and `rigsfm report OUT`.
"""

import argparse
import csv
import json
from pathlib import Path

from rigsfm.associate import AssociateOptions, associate, load_run
from rigsfm.associate.evaluate import make_detections, score_groups, visible_heads
from rigsfm.inspect.report.write import write_report
from rigsfm.run.pipeline import RunOptions, run
from rigsfm.synth.dataset import render_dataset, scale_with_floor_bar
from rigsfm.synth.scene import SceneOptions
from rigsfm.synth.truth import compare_to_ground_truth


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--num-rigs", type=int, default=8)
    parser.add_argument("--arc-deg", type=float, default=360.0)
    parser.add_argument("--image-scale", type=float, default=0.5)
    args = parser.parse_args(argv)

    # 1. The scene, and a scale.yaml whose known length lies on the floor (the persons stand on it).
    scene = SceneOptions(num_rigs=args.num_rigs, arc_deg=args.arc_deg, image_scale=args.image_scale, seed=1,
                         persons_per_m2=4.0, narrow_extra_pitch_deg=-4.0)
    dataset = render_dataset(args.out / "scene", scene)
    scale = scale_with_floor_bar(dataset, args.out / "scale.yaml")

    # 2. The calibration: every default (the narrow observations decide themselves whether the heads are usable).
    result = run(dataset.images, dataset.rigs, args.out / "run", scale, RunOptions())
    narrow = compare_to_ground_truth(result.reconstruction, dataset.load_ground_truth(), "narrow")
    record = result.summary.narrow_observations
    used = f"{'used' if record.used else 'not used'}: {record.reason}" if record else "not asked"
    print(f"narrow relative rotation error: median {narrow['relative_rotation_deg']['median']:.4f} deg, "
          f"max {narrow['relative_rotation_deg']['max']:.4f} deg (narrow observations: {used})")

    # 3. Your detector's heads: here the true visible heads, made as noisy as a detector's.
    model = load_run(args.out / "run")
    sizes = {name: (image.camera.width, image.camera.height) for name, image in model.images.items()}
    heads = {name: v for name, v in visible_heads(dataset.root, "frame0000").items() if name in sizes}
    truth = make_detections(heads, sizes, sigma_px=1.5, missed=0.1, false=0.05, seed=0)
    detections = args.out / "heads.csv"
    detections.write_text(truth.csv_text())

    # 4. The same person in every narrow view, then joined back to the CSV's rows.
    persons_dir = associate(args.out / "run", detections, AssociateOptions())  # the detector's noise: the crowd's
    persons = json.loads((persons_dir / "frame0000" / "persons.json").read_text())["persons"]
    with open(detections, newline="") as file:
        rows = list(csv.DictReader(file))  # persons.json's "row" counts the header as line 1
    index = {}
    for image, xy in truth.points.items():
        for i, _ in enumerate(xy):
            index[len(index) + 2] = (image, i)
    groups = [[index[d["row"]] for d in person["detections"]] for person in persons]
    assert all(rows[d["row"] - 2]["image"] == d["image"] for person in persons for d in person["detections"])
    scores = score_groups(groups, truth)
    print(f"persons: {len(persons)} found ({scores.true_persons} true persons in two or more views); pairs of "
          f"detections put together: precision {scores.pair_precision:.3f}, recall {scores.pair_recall:.3f}")
    print(f"report: {write_report(args.out / 'run')}")
    return {"narrow": narrow, "persons": len(persons), "pair_f1": scores.pair_f1,
            "pair_precision": scores.pair_precision, "pair_recall": scores.pair_recall}


if __name__ == "__main__":
    main()
