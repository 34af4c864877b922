"""Command-line entry point: ``jaxlimits <command>`` (or ``python -m jaxlimits.training.cli``)."""

from __future__ import annotations

import argparse
import sys

from jaxlimits._xla_flags import set_cpu_xla_flags


def main(argv=None) -> int:
    set_cpu_xla_flags()
    parser = argparse.ArgumentParser(prog="jaxlimits", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="Del Prete 2018 Sec. V-A: naive vs viability bounds on one joint")
    demo.add_argument("--out", default="results/demo", help="folder for results.json and joint_space.png")
    demo.add_argument("--no-plot", action="store_true", help="skip the PNG")
    args = parser.parse_args(argv)
    if args.command == "demo":
        from jaxlimits.training.joint_space_demo import run

        run(args.out, plot=not args.no_plot)
        print(f"wrote {args.out}/results.json" + ("" if args.no_plot else f" and {args.out}/joint_space.png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
