"""The ``lgs-wfs`` command: demo, report, inspect, replay, reproduce, train, recover.

Every verb calls the same library functions the nodes and the tests use. Errors the user can fix
(a missing or corrupt bag, a bad option) print one line and exit with code 2, no traceback.
"""

from __future__ import annotations

import argparse
import sys


def _demo(args):
    from .extras import require
    require("rclpy", "ros", "lgs-wfs demo")
    from .ros.demo import run_demo
    return run_demo(out_dir=args.out_dir, single_frames=args.frames, full_frames=args.full_frames,
                    full_rate_hz=args.full_rate, algorithms=args.algorithms.split(","))


def _inspect(args):
    from .analysis.inspect import inspect_bag
    print(inspect_bag(args.bag, as_json=args.json))
    return 0


def _report(args):
    from .analysis.report import report_bag
    return report_bag(args.bag, out_dir=args.out, as_json=args.json, skip=args.skip)


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
    from .learning import train_model
    train_model(args.name, out_dir=args.out, samples=args.samples, seed=args.seed,
                quick=args.quick, force=args.force)
    return 0


def _recover(args):
    from .bags import recover_command
    return recover_command(args.src, args.dst, overwrite=args.overwrite)


#: each subcommand's examples, shown at the end of its --help (test_cli_help parses them)
EXAMPLES = {
    "demo": ('  lgs-wfs demo                                  # both runs, bags under bags/\n'
             '  lgs-wfs demo --frames 300 --full-frames 0 --algorithms cog,cmf   # quick\n'),
    "inspect": ('  lgs-wfs inspect bags/sample.mcap\n'
                '  lgs-wfs inspect bags/sample.mcap --json\n'),
    "report": ('  lgs-wfs report bags/sample.mcap\n'
               '  lgs-wfs report bags/sample.mcap --out report/   # + PNGs and summary.json\n'),
    "replay": ('  lgs-wfs replay bags/sample.mcap --algorithms cog,cmf --out replayed.mcap\n'
               '  lgs-wfs replay bags/sample.mcap --algorithms ann --models ann_pupil,ann_1k\n'
               '  lgs-wfs replay bags/sample.mcap --algorithms cmf --options \'{"cmf": {"reference": "model"}}\'\n'),
    "reproduce": ('  lgs-wfs reproduce --quick                  # into a new temporary directory\n'
                  '  lgs-wfs reproduce --quick --out /tmp/repro\n'
                  '  lgs-wfs reproduce --update-docs            # regenerate docs/reproduction.md\n'),
    "train": ('  lgs-wfs train ann_1k --quick --out /tmp/models\n'
              '  lgs-wfs train ann_1k --out models --force    # replace the shipped model\n'),
    "recover": ('  lgs-wfs recover damaged.mcap fixed.mcap\n'),
}


def _add(sub, name: str, func, help: str, positionals=()) -> argparse.ArgumentParser:
    """The subcommand ``name`` running ``func(args)``, its ``positionals`` given as
    ``(name, help)`` pairs; its --help ends with ``EXAMPLES[name]``."""
    p = sub.add_parser(name, help=help, description=help[:1].upper() + help[1:] + ".",
                       epilog="examples:\n" + EXAMPLES[name],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    for arg, text in positionals:
        p.add_argument(arg, help=text)
    p.set_defaults(func=func)
    return p


def _flag(p: argparse.ArgumentParser, name: str, help: str) -> None:
    """An on/off option (false unless given)."""
    p.add_argument(name, action="store_true", help=help)


def _out_dir(p: argparse.ArgumentParser, what: str, default: str) -> None:
    """The ``--out DIR`` option of a verb that writes files."""
    p.add_argument("--out", default=None, metavar="DIR",
                   help=f"directory for {what} (default: {default})")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="lgs-wfs", description="LGS Shack-Hartmann centroiding: simulate, centroid, "
        "record, analyse.", formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  lgs-wfs demo\n  lgs-wfs inspect bags/sample.mcap\n"
               "  lgs-wfs report bags/sample.mcap --out report/\n"
               "'lgs-wfs <command> --help' explains each command's options.")
    sub = ap.add_subparsers(dest="verb", required=True, metavar="command")

    p = _add(sub, "demo", _demo, "run simulator + centroiders + recorder as ROS 2 node processes, "
             "then print the error table of each bag")
    p.add_argument("--out-dir", default="bags", metavar="DIR",
                   help="directory for the bags and their node logs (default: %(default)s)")
    p.add_argument("--frames", type=int, default=2100,
                   help="frames of the paper's single-subaperture case at 700 Hz "
                        "(0: skip that run; default: %(default)s)")
    p.add_argument("--full-frames", type=int, default=980,
                   help="frames of the full 60 x 60 pupil run, the first 700 (the pupil "
                        "calibration's warm-up, five refit periods) left out of its table "
                        "(0: skip it; default: %(default)s)")
    p.add_argument("--full-rate", type=float, default=0.0, metavar="HZ",
                   help="full-pupil frame rate in Hz (0: the highest measured to hold here)")
    p.add_argument("--algorithms", default="cog,cmf,ann", metavar="A,B,...",
                   help="centroiders run side by side, comma-separated, from cog, tcog, wcog, "
                        "cmf, corr, ann, ml, gmf (ml: polar detector only; default: %(default)s)")

    p = _add(sub, "inspect", _inspect, "topics, counts, rates, sensor and centroider changes of a bag",
             positionals=[("bag", "an MCAP bag (any recorder)")])
    _flag(p, "--json", "print JSON instead of text")

    p = _add(sub, "report", _report, "per-algorithm errors, CRB, plots and a JSON summary of a bag",
             positionals=[("bag", "an MCAP bag with frames or slopes and true_slopes")])
    _out_dir(p, "PNGs and summary.json", "print the tables only")
    _flag(p, "--json", "print the JSON summary alone")
    p.add_argument("--skip", type=int, default=0, metavar="N",
                   help="leave out the first N exposures, e.g. 140: a pupil-calibrated "
                        "centroider's first refit period (default 0)")

    p = _add(sub, "replay", _replay, "run centroiders over a bag's frames into a new bag (no ROS); "
             "each uses the options recorded in the bag for its algorithm unless --options",
             positionals=[("bag", "input MCAP bag with frame and sensor topics, e.g. bags/full.mcap")])
    p.add_argument("--algorithms", default="cog,cmf,ann",
                   help="comma-separated centroiders, e.g. cog,cmf,corr,ann (default cog,cmf,ann)")
    p.add_argument("--out", default=None,
                   help="output bag, e.g. bags/full_replay.mcap (default <bag stem>_replay.mcap)")
    _flag(p, "--overwrite", "replace an existing output bag")
    p.add_argument("--model", default=None,
                   help="ONNX model for ann, a name in models/ or a path, e.g. ann_pupil")
    p.add_argument("--models", default=None,
                   help="several ONNX models, ann runs once per model into /ann_<name>, "
                        "e.g. ann_pupil,ann_1k")
    p.add_argument("--options", default=None,
                   help="JSON {algorithm: {option: value}} replacing the recorded options of those "
                        "algorithms (others keep the bag's, or the defaults), or @file.json, e.g. "
                        "'{\"cmf\": {\"reference\": \"history\"}, \"cog\": {\"bias\": \"pupil\"}}'")

    p = _add(sub, "reproduce", _reproduce, "the paper's figures and tables with our code")
    _flag(p, "--quick", "fewer frames and a shorter validation run")
    _out_dir(p, "reproduction.md/.json and figures/", "a new temporary one")
    _flag(p, "--update-docs", "write into the checkout's docs/ instead (the tracked report)")
    _flag(p, "--allow-fail", "exit 0 even when a check fails (default: exit 1)")

    p = _add(sub, "train", _train, "retrain a model from scratch (needs the 'train' extra)",
             positionals=[("name", "a shipped model's name (its recipe), e.g. ann_1k")])
    _flag(p, "--force", "replace an existing --out/NAME.onnx")
    _out_dir(p, "NAME.onnx and its README.md card", "a new temporary one")
    p.add_argument("--samples", type=int, default=None, help="training samples (default: the recipe's)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: the recipe's)")
    _flag(p, "--quick", "a small quick run, for tests")

    p = _add(sub, "recover", _recover, "copy every readable message of a damaged bag to a new bag",
             positionals=[("src", "the damaged (e.g. cut-off) MCAP bag"), ("dst", "the bag to write")])
    _flag(p, "--overwrite", "replace dst if it exists")
    return ap


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    from .bags import BagError
    from .extras import MissingExtra
    try:
        return int(args.func(args) or 0)
    except (BagError, MissingExtra, ValueError, FileNotFoundError, FileExistsError) as exc:
        print(f"lgs-wfs {args.verb}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
