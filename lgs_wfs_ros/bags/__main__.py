"""``python -m lgs_wfs_ros.bags info BAG`` / ``recover SRC DST [--overwrite]`` / ``scrub SRC DST``.

The same functions the ``lgs-wfs`` CLI wires (``lgs-wfs recover``); here so the recovery
command works from any install. Exit codes: 0 done, 1 recovered with problems, 2 refused."""

import argparse
import json
import sys

from . import BagError, BagReader, recover_command


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m lgs_wfs_ros.bags", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("info", help="topics, counts, times of a bag (JSON)")
    p.add_argument("bag")
    p.add_argument("--lenient", action="store_true", help="report a damaged bag instead of refusing it")
    p = sub.add_parser("recover", help="copy every readable message of a damaged bag into a new bag")
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--overwrite", action="store_true")
    p = sub.add_parser("scrub", help="copy a bag with names instead of absolute paths in its JSON messages")
    p.add_argument("src")
    p.add_argument("dst")
    p.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    try:
        if args.cmd == "info":
            with BagReader(args.bag, strict=not args.lenient) as r:
                print(json.dumps(r.summary(), indent=2))
            return 0
        if args.cmd == "scrub":
            from .portable import scrub_bag
            print(json.dumps(scrub_bag(args.src, args.dst, overwrite=args.overwrite), indent=2))
            return 0
        return recover_command(args.src, args.dst, overwrite=args.overwrite)
    except BagError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
