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
    return reproduce(quick=args.quick, out_dir=args.out, update_docs=args.update_docs,
                     allow_fail=args.allow_fail)


def _train(args):
    from .extras import MissingExtra
    from .learning import train_model
    try:
        train_model(args.name, out_dir=args.out, samples=args.samples, seed=args.seed,
                    quick=args.quick, force=args.force)
    except MissingExtra as exc:
        print(f"lgs-wfs train: {exc}", file=sys.stderr)
        return 2
    return 0


def _recover(args):
    from .bags import recover_command
    return recover_command(args.src, args.dst, overwrite=args.overwrite)


def _add(sub, name: str, help: str, examples: str) -> argparse.ArgumentParser:
    """A subcommand whose --help ends with its examples."""
    return sub.add_parser(name, help=help, description=help[:1].upper() + help[1:] + ".",
                          epilog="examples:\n" + examples,
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="lgs-wfs", description="LGS Shack-Hartmann centroiding: simulate, centroid, "
        "record, analyse.", formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  lgs-wfs demo\n  lgs-wfs inspect bags/sample.mcap\n"
               "  lgs-wfs report bags/sample.mcap --out report/\n"
               "'lgs-wfs <command> --help' explains each command's options.")
    sub = ap.add_subparsers(dest="verb", required=True, metavar="command")

    p = _add(sub, "demo", "run simulator + centroiders + recorder as ROS 2 node processes, "
             "then print the error table of each bag",
             "  lgs-wfs demo                                  # both runs, bags under bags/\n"
             "  lgs-wfs demo --frames 300 --full-frames 0 --algorithms cog,cmf   # quick\n")
    p.add_argument("--out-dir", default="bags", metavar="DIR",
                   help="directory for the bags and their node logs (default: %(default)s)")
    p.add_argument("--frames", type=int, default=2100,
                   help="frames of the paper's single-subaperture case at 700 Hz "
                        "(0: skip that run; default: %(default)s)")
    p.add_argument("--full-frames", type=int, default=100,
                   help="frames of the full 60 x 60 pupil run (0: skip it; default: %(default)s)")
    p.add_argument("--full-rate", type=float, default=0.0, metavar="HZ",
                   help="full-pupil frame rate in Hz (0: the highest measured to hold here)")
    p.add_argument("--algorithms", default="cog,cmf,ann", metavar="A,B,...",
                   help="centroiders run side by side, comma-separated, from cog, tcog, wcog, "
                        "cmf, corr, ann (default: %(default)s)")
    p.set_defaults(func=_demo)

    p = _add(sub, "inspect", "topics, counts, rates, sensor and centroider changes of a bag",
             "  lgs-wfs inspect bags/sample.mcap\n  lgs-wfs inspect bags/sample.mcap --json\n")
    p.add_argument("bag", help="an MCAP bag (any recorder)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=_inspect)

    p = _add(sub, "report", "per-algorithm errors, CRB, plots and a JSON summary of a bag",
             "  lgs-wfs report bags/sample.mcap\n"
             "  lgs-wfs report bags/sample.mcap --out report/   # + PNGs and summary.json\n")
    p.add_argument("bag", help="an MCAP bag with frames or slopes and true_slopes")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="directory for PNGs and summary.json (default: print the tables only)")
    p.add_argument("--json", action="store_true", help="print the JSON summary alone")
    p.set_defaults(func=_report)

    p = _add(sub, "replay", "run centroiders over a bag's frames into a new bag (no ROS); each "
             "uses the options recorded in the bag for its algorithm unless --options",
             "  lgs-wfs replay bags/sample.mcap --algorithms cog,cmf --out replayed.mcap\n"
             "  lgs-wfs replay bags/sample.mcap --algorithms ann --models ann_pupil,ann_1k\n"
             "  lgs-wfs replay bags/sample.mcap --algorithms cmf --options '{\"cmf\": {\"reference\": \"model\"}}'\n")
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

    p = _add(sub, "reproduce", "the paper's figures and tables with our code",
             "  lgs-wfs reproduce --quick                  # into a new temporary directory\n"
             "  lgs-wfs reproduce --quick --out /tmp/repro\n"
             "  lgs-wfs reproduce --update-docs            # regenerate docs/reproduction.md\n")
    p.add_argument("--quick", action="store_true", help="fewer frames and a shorter validation run")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="directory for reproduction.md/.json and figures/ (default: a new temporary one)")
    p.add_argument("--update-docs", action="store_true",
                   help="write into the checkout's docs/ instead (the tracked report)")
    p.add_argument("--allow-fail", action="store_true",
                   help="exit 0 even when a check fails (default: exit 1)")
    p.set_defaults(func=_reproduce)

    p = _add(sub, "train", "retrain a model from scratch (needs the 'train' extra)",
             "  lgs-wfs train ann_1k --quick --out /tmp/models\n"
             "  lgs-wfs train ann_1k --out models --force    # replace the shipped model\n")
    p.add_argument("name", help="a shipped model's name (its recipe), e.g. ann_1k")
    p.add_argument("--out", default=None, metavar="DIR",
                   help="directory for NAME.onnx and its README.md card (default: a new temporary one)")
    p.add_argument("--force", action="store_true", help="replace an existing --out/NAME.onnx")
    p.add_argument("--samples", type=int, default=None, help="training samples (default: the recipe's)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the recipe's)")
    p.add_argument("--quick", action="store_true", help="a small quick run, for tests")
    p.set_defaults(func=_train)

    p = _add(sub, "recover", "copy every readable message of a damaged bag to a new bag",
             "  lgs-wfs recover damaged.mcap fixed.mcap\n")
    p.add_argument("src", help="the damaged (e.g. cut-off) MCAP bag")
    p.add_argument("dst", help="the bag to write")
    p.add_argument("--overwrite", action="store_true", help="replace dst if it exists")
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
