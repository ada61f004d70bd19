"""Run every benchmark and write benchmarks/results.json plus a short table.

    python benchmarks/run.py [--quick] [--only simulator,centroiders]
    python benchmarks/run.py --fold OUT.json    # fold bench_transport.py --json rows in

Each ``benchmarks/bench_<area>.py`` exposes ``run(quick=False) -> list[dict]`` with rows
``{"name", "value", "unit", "target", "note"}``. A ``bench_*.py`` without ``run`` is a
standalone script with outputs of its own (``bench_ann_ref.py``: the reference-reading
network on the accuracy benchmark's cases, hours of CPU, ``accuracy_ann_ref.json``): listed,
not run. Everything runs on one thread (numpy's BLAS,
onnxruntime's intra-op pool): the targets are per core.
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

HERE = Path(__file__).resolve().parent


def load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fold(cases_json: Path, out: Path) -> int:
    """The issue-18 rows of ``bench_transport.py --json`` into ``out``'s 'transport' area
    (flattened to name/value/unit/target/note, each case kept beside its first row)."""
    cases = json.loads(cases_json.read_text())
    rows = [r for case in cases for r in load(HERE / "bench_transport.py").flat_rows(case)]
    results = json.loads(out.read_text()) if out.exists() else {"areas": {}}
    results.setdefault("areas", {})["transport"] = {
        "rows": rows, "folded_from": cases_json.name,
        "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"folded {len(cases)} cases ({len(rows)} rows) into {out}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats")
    ap.add_argument("--only", default="", help="comma-separated areas (file names without bench_)")
    ap.add_argument("--out", default=str(HERE / "results.json"))
    ap.add_argument("--fold", default="", help="a bench_transport.py --json file: its rows "
                    "become the 'transport' area (nothing is rerun)")
    args = ap.parse_args(argv)
    if args.fold:
        return fold(Path(args.fold), Path(args.out))
    only = {a.strip() for a in args.only.split(",") if a.strip()}
    results = {"machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                           "platform": platform.platform()},
               "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "areas": {}}
    failed = 0
    for path in sorted(HERE.glob("bench_*.py")):
        area = path.stem[len("bench_"):]
        if only and area not in only:
            continue
        print(f"== {area}", flush=True)
        t0 = time.perf_counter()
        try:
            module = load(path)
            if not hasattr(module, "run"):
                print(f"  standalone (no run()): python benchmarks/{path.name}", flush=True)
                continue
            rows = module.run(quick=args.quick)
        except Exception:
            traceback.print_exc()
            failed += 1
            results["areas"][area] = {"error": traceback.format_exc(limit=3)}
            continue
        results["areas"][area] = {"rows": rows, "seconds": round(time.perf_counter() - t0, 1)}
        for r in rows:
            print(f"  {r['name']:<48} {r['value']:>12.4g} {r['unit']:<10} target {r.get('target', '')}")
    if only and Path(args.out).exists():   # keep the areas that were not rerun
        old = json.loads(Path(args.out).read_text())
        for area, value in old.get("areas", {}).items():
            results["areas"].setdefault(area, value)
    Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
