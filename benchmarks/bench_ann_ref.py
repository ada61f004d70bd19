"""Accuracy of the reference-reading network (ann_ref) beside cog, cmf and the CRB.

Runs ``bench_accuracy.run_case`` (the same frames, tilts, unseen families, CRB and scores as
the accuracy benchmark) with ``ann_ref`` added to its estimators, on the quick cases (or a
subset: ``--cases N``), writes ``benchmarks/accuracy_ann_ref.json`` and a markdown table,
and records the summary in the model's ``lgs_wfs.training["accuracy"]`` (so the model card,
``learning/card.py``, shows it).

    python benchmarks/bench_ann_ref.py [--cases N] [--model ann_ref] [--record]
    python benchmarks/bench_ann_ref.py --tables12 [--model ann_marg]   # tables12_<model>.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import bench_accuracy as acc  # noqa: E402

LABELS = ("cog", "cog_pupil", "cmf", "ann_ref")


def table(cases) -> str:
    lines = ["| family | detector | launch (m) | tilts | photons | " + " | ".join(LABELS)
             + " | CRB | ann_ref / CRB | ann_ref / cog | ann_ref / best classical |",
             "|---|---|---|---|---|" + "---|" * (len(LABELS) + 4)]
    for c in cases:
        for ph, row in c["photons"].items():
            if "ann_ref" not in row:
                continue
            best = min(row[lb]["mean_2d_mas"] for lb in ("cog", "cog_pupil", "cmf") if lb in row)
            a = row["ann_ref"]["mean_2d_mas"]
            lines.append(f"| {c['family']} | {c['detector']} | {c['launch_m']:g} | {c['tilts']} | {ph} | "
                         + " | ".join(f"{row[lb]['mean_2d_mas']:.1f}" if lb in row else "-" for lb in LABELS)
                         + f" | {c['crb'][ph]['mean_2d_mas']:.1f} | {a / c['crb'][ph]['mean_2d_mas']:.2f} | "
                         f"{a / row['cog']['mean_2d_mas']:.2f} | {a / best:.2f} |")
    return "\n".join(lines) + "\n"


def summary(cases) -> dict:
    """Per family: mean ratio of ann_ref to the CRB and to cog over its cases."""
    return acc.family_summary(cases, "ann_ref")


PAPER_T12 = {"polar": 0.249, "cartesian": 0.224}     # the paper's ANN / CoG, Tables 1-2 (text)


def tables_12(model: str, iterations: int = 5000, seed: int = 2014) -> list[dict]:
    """The paper's Tables 1-2 cases (one subaperture at r = 14.75 m, the uncentred profile,
    independent turbulent positions; polar / cartesian on the diagonal; 316 and 1000 photons),
    as ``lgs_wfs_ros.analysis.reproduce.run_sweep`` draws them: the mean 2-D error (mas) of
    cog, the paper-faithful MLP (paper prior), the shipped MLP and ``model`` (its reference
    from a single-subaperture pupil calibration), frame by frame."""
    from lgs_wfs_ros.analysis import reproduce as rp
    from lgs_wfs_ros.centroiding import options as table
    from lgs_wfs_ros.optics import sodium
    from lgs_wfs_ros.sensor import Sensor
    rows = []
    for case in ("turbulent", "diagonal"):
        spec = rp.CASES[case]
        sensor = Sensor.paper_single(spec["detector"])
        h = rp.altitude_grid()
        rho = sodium.paper_profile(spec["profile"], h)
        truths = rp.independent_tilts(sensor, iterations, seed + 1)
        images = rp.expected_images(sensor, h, rho, truths)
        rng = np.random.default_rng([seed, list(rp.CASES).index(case)])
        det = spec["detector"]
        labels = {"cog": ("cog", {}), model: ("ann", {"model": model}),
                  "paper-faithful MLP": ("ann", {"model": "paper_prior/ann_1k_paper" if det == "polar"
                                                 else "paper_prior/ann_diag_paper"}),
                  "shipped MLP": ("ann", {"model": "ann_1k" if det == "polar" else "ann_diag"})}
        for ph in (316, 1000):
            frames = rng.poisson(images * ph).astype(np.float32)
            cents = {}
            for lb, (a, o) in labels.items():
                try:
                    cents[lb] = table.build(a, sensor.replace(photons=float(ph)), o)
                except ValueError as exc:           # ann_marg: polar only
                    print(f"  {lb} on {det}: not run ({exc})", flush=True)
            err = {lb: float(np.mean(np.linalg.norm(rp.run_centroiders({lb: c}, frames)[lb] - truths, axis=1)))
                   * acc.MAS for lb, c in cents.items()}
            row = {"detector": det, "photons": ph, "mas": err,
                   "ratio_cog": {lb: v / err["cog"] for lb, v in err.items()}, "paper_ann_over_cog": PAPER_T12[det]}
            print(row, flush=True)
            rows.append(row)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=0, help="first N quick cases only (0: all)")
    ap.add_argument("--model", default="ann_ref")
    ap.add_argument("--warm", type=int, default=210)
    ap.add_argument("--scored", type=int, default=140)
    ap.add_argument("--record", action="store_true", help="write the summary into the model's metadata")
    ap.add_argument("--tables12", action="store_true", help="only the paper's Tables 1-2 cases")
    ap.add_argument("--select", default="", help="comma-separated indices of the quick cases to run "
                    "(parallel parts), written to accuracy_ann_ref.part<first>.json")
    ap.add_argument("--merge", action="store_true", help="merge the part files, then table and --record")
    args = ap.parse_args(argv)
    if args.tables12:
        rows = tables_12(args.model)
        name = Path(args.model).stem
        (HERE / f"tables12_{name}.json").write_text(json.dumps(rows, indent=1) + "\n")
        return 0
    acc.ESTIMATORS["ann_ref"] = ("ann", {"model": args.model})
    cases = acc.quick_cases()
    cases = cases[:args.cases] if args.cases else cases
    out = []
    if args.merge:
        parts = sorted(HERE.glob("accuracy_ann_ref.part*.json"))
        out = [c for f in parts for c in json.loads(f.read_text())]
    elif args.select:
        idx = [int(i) for i in args.select.split(",")]
        for i in idx:
            out.append(acc.run_case(*cases[i], args.warm, args.scored, LABELS))
            (HERE / f"accuracy_ann_ref.part{idx[0]}.json").write_text(json.dumps(out, indent=1) + "\n")
        return 0
    else:
        for fam, det, launch, tilt in cases:
            out.append(acc.run_case(fam, det, launch, tilt, args.warm, args.scored, LABELS))
    res = {"what": f"bench_accuracy.run_case, {args.warm} warm-up + {args.scored} scored frames, "
                   f"model {args.model}", "cases": out, "summary": summary(out)}
    (HERE / "accuracy_ann_ref.json").write_text(json.dumps(res, indent=1) + "\n")
    md = table(out)
    (HERE / "accuracy_ann_ref.md").write_text(md)
    doc = HERE.parent / "docs" / "ann_ref.md"
    begin, end = "<!-- numbers:begin -->", "<!-- numbers:end -->"
    text = doc.read_text() if doc.is_file() else ""
    if begin in text and end in text:
        block = (f"{begin}\n(generated by `python benchmarks/bench_ann_ref.py`; {res['what']}; "
                 "mean 2-D error, mas; cog_pupil = cog with the pupil-calibrated bias removed; "
                 "best classical = the best of cog, cog_pupil, cmf)\n\n" + md + end)
        doc.write_text(text[:text.index(begin)] + block + text[text.index(end) + len(end):])
    print(md)
    print(json.dumps(res["summary"], indent=1))
    if args.record:
        from lgs_wfs_ros.centroiding.ann_model import resolve_model
        from lgs_wfs_ros.learning import card, export
        path = resolve_model(args.model)
        tr = export.read_metadata(path).get("lgs_wfs.training", {})
        tr["accuracy"] = {"what": res["what"], "per_family": res["summary"],
                          "cpu_ms_per_frame": {c["family"] + "/" + c["detector"] + f"/{c['launch_m']:g}":
                                               round(c["cpu_ms"]["ann_ref"]["per_frame"], 2) for c in out
                                               if "ann_ref" in c["cpu_ms"]}}
        export.update_metadata(path, {"lgs_wfs.training": tr})
        card.write(path.parent)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
