"""The ``lgs-wfs`` command: demo, report, inspect, replay, reproduce, train, recover.

Every verb calls the same library functions the nodes and the tests use. Errors the user can fix
(a missing or corrupt bag, a bad option) print one line and exit with code 2, no traceback.
"""

from __future__ import annotations

import argparse
import sys


def _demo(args):
    from .ros.demo import run_demo
    return run_demo(out_dir=args.out_dir, single_frames=args.frames, full_frames=args.full_frames,
                    full_rate_hz=args.full_rate, algorithms=args.algorithms.split(","))


def _inspect(args):
    from .analysis.inspect import inspect_bag
    print(inspect_bag(args.bag, as_json=args.json))
    return 0


def _report(args):
    from .analysis.report import report_bag
    return report_bag(args.bag, out_dir=args.out, as_json=args.json)


def _replay(args):
    import json
    from pathlib import Path
    from .analysis.replay import replay_bag
    opts = None
    if args.options:
        text = args.options
        if text.startswith("@"):
            text = Path(text[1:]).read_text()
        try:
            opts = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"--options is not JSON ({exc}); e.g. '{{\"cmf\": {{\"reference\": \"history\"}}}}'")
    models = [m for m in (args.models or "").split(",") if m]
    replay_bag(args.bag, algorithms=args.algorithms.split(","), out=args.out,
               overwrite=args.overwrite, model=args.model, models=models, options=opts)
    return 0


def _reproduce(args):
    from .analysis.reproduce import reproduce
    return reproduce(quick=args.quick, out_dir=args.out)


def _train(args):
    from .learning.train import train_model
    train_model(args.name, out_dir=args.out, samples=args.samples, seed=args.seed,
                quick=args.quick)
    return 0


def _recover(args):
    from .bags import recover
    stats = recover(args.src, args.dst)
    print(f"recovered {stats}")
    return 0


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="lgs-wfs", description="LGS Shack-Hartmann centroiding: "
                                 "simulate, centroid, record, analyse.")
    sub = ap.add_subparsers(dest="verb", required=True)

    p = sub.add_parser("demo", help="run simulator + centroiders + recorder, print the error table")
    p.add_argument("--out-dir", default="bags")
    p.add_argument("--frames", type=int, default=2100,
                   help="frames of the paper's single-subaperture case at 700 Hz")
    p.add_argument("--full-frames", type=int, default=100, help="full-pupil frames")
    p.add_argument("--full-rate", type=float, default=0.0,
                   help="full-pupil frame rate in Hz (0: the highest measured to hold)")
    p.add_argument("--algorithms", default="cog,cmf,ann")
    p.set_defaults(func=_demo)

    p = sub.add_parser("inspect", help="topics, counts, rates, sensor and centroider changes of a bag")
    p.add_argument("bag")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=_inspect)

    p = sub.add_parser("report", help="per-algorithm errors, CRB, plots and a JSON summary of a bag")
    p.add_argument("bag")
    p.add_argument("--out", default=None, help="directory for PNGs and summary.json")
    p.add_argument("--json", action="store_true", help="print the JSON summary alone")
    p.set_defaults(func=_report)

    p = sub.add_parser("replay", help="run centroiders over a bag's frames into a new bag (no ROS); "
                       "each uses the options recorded in the bag for its algorithm unless --options")
    p.add_argument("bag", help="input MCAP bag with frame and sensor topics, e.g. bags/full.mcap")
    p.add_argument("--algorithms", default="cog,cmf,ann",
                   help="comma-separated centroiders, e.g. cog,cmf,corr,ann (default cog,cmf,ann)")
    p.add_argument("--out", default=None,
                   help="output bag, e.g. bags/full_replay.mcap (default <bag stem>_replay.mcap)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output bag")
    p.add_argument("--model", default=None,
                   help="ONNX model for ann, a name in models/ or a path, e.g. ann_pupil")
    p.add_argument("--models", default=None,
                   help="several ONNX models, ann runs once per model into /ann_<name>, "
                        "e.g. ann_pupil,ann_1k")
    p.add_argument("--options", default=None,
                   help="JSON {algorithm: {option: value}} replacing the recorded options of those "
                        "algorithms (others keep the bag's, or the defaults), or @file.json, e.g. "
                        "'{\"cmf\": {\"reference\": \"history\"}, \"cog\": {\"bias\": \"pupil\"}}'")
    p.set_defaults(func=_replay)

    p = sub.add_parser("reproduce", help="the paper's figures and tables with our code")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", default="docs")
    p.set_defaults(func=_reproduce)

    p = sub.add_parser("train", help="retrain a shipped model from scratch (needs .[train])")
    p.add_argument("name")
    p.add_argument("--out", default="models")
    p.add_argument("--samples", type=int, default=None)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--quick", action="store_true")
    p.set_defaults(func=_train)

    p = sub.add_parser("recover", help="copy every readable message of a damaged bag to a new bag")
    p.add_argument("src")
    p.add_argument("dst")
    p.set_defaults(func=_recover)
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    from .bags import BagError
    try:
        return int(args.func(args) or 0)
    except BagError as exc:
        print(f"lgs-wfs {args.verb}: {exc}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"lgs-wfs {args.verb}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
