"""The ``ngp-mi`` command. Sub-commands only parse arguments and call library functions."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence


def _doctor(args: argparse.Namespace) -> int:
    from ngp_mi.doctor import run_doctor

    return run_doctor()


def _demo(args: argparse.Namespace) -> int:
    from ngp_mi.demo import run_demo

    run_demo(args.out, resolution=args.res, views=args.views, spp=args.spp, seed=args.seed)
    return 0


def _families(args: argparse.Namespace) -> int:
    from ngp_mi.demo import family_sheet

    path = family_sheet(args.family, args.out or f"outputs/families/{args.family}.png", count=args.count,
                        resolution=args.res, spp=args.spp, first_seed=args.seed)
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ngp-mi", description="Neural Graphics Pipeline on Mitsuba 3 / Dr.Jit and PyTorch.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")

    doctor = sub.add_parser("doctor", help="print versions, backend and a timed test render; exit 0 if rendering works",
                            description="Print versions, the Mitsuba variant, libLLVM and a timed test render.")
    doctor.set_defaults(func=_doctor)

    demo = sub.add_parser("demo", help="render the showcase contact sheets under outputs/demo",
                          description="Path trace a procedural chair from the paper's view distribution "
                                      "under the 4-light overhead rig, and 16 samples of each shape family.")
    demo.add_argument("--out", default="outputs/demo", help="output folder (default: %(default)s)")
    demo.add_argument("--res", type=int, default=128, help="image size in pixels (default: %(default)s)")
    demo.add_argument("--views", type=int, default=12, help="number of sampled views (default: %(default)s)")
    demo.add_argument("--spp", type=int, default=64, help="samples per pixel (default: %(default)s)")
    demo.add_argument("--seed", type=int, default=0, help="random seed for views and noise (default: %(default)s)")
    demo.set_defaults(func=_demo)

    families = sub.add_parser("families", help="contact sheet of samples of a procedural shape family",
                              description="Path trace consecutive seeds of a procedural family (chair, car) "
                                          "with their part materials into one contact sheet.")
    families.add_argument("family", choices=["chair", "car"], help="shape family")
    families.add_argument("--count", type=int, default=16, help="number of samples (default: %(default)s)")
    families.add_argument("--seed", type=int, default=0, help="first seed (default: %(default)s)")
    families.add_argument("--res", type=int, default=128, help="image size (default: %(default)s)")
    families.add_argument("--spp", type=int, default=32, help="samples per pixel (default: %(default)s)")
    families.add_argument("--out", help="PNG path (default: outputs/families/FAMILY.png)")
    families.set_defaults(func=_families)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from ngp_mi.backend import BackendError

    try:
        return int(args.func(args) or 0)
    except (BackendError, ValueError) as error:
        print(f"ngp-mi {args.command}: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
