"""``torchmetal plan CAPTURE_OR_MATERIAL [-n K] -o DIR`` (docs/design.md §2.5): the next K photos to take; and
``torchmetal intervals MATERIAL CAPTURE``: the leave-out intervals of a fitted material (:mod:`torchmetal.plan.intervals`).

Imports only argparse at the top (``--help`` stays instant); the verb's function does the heavy imports.
"""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``plan`` verb."""
    p = sub.add_parser("plan", help="the next K flash photos to take (DIR/plan.json, DIR/plan.png)",
                       description="Propose the next K flash/camera positions a hand-held phone can reach that most lower "
                                   "the expected error of renders under views not photographed (I-optimal on the fit's "
                                   "information) and put the highlight where no photo has put it yet.")
    p.add_argument("source", metavar="CAPTURE_OR_MATERIAL", help="capture directory (fitted quickly first) or material")
    p.add_argument("-n", "--shots", type=int, default=3, metavar="K", help="shots to plan (default: %(default)s)")
    p.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for plan.json and plan.png")
    p.add_argument("--capture", default=None, help="with a material: its capture, whose shots were taken already")
    p.set_defaults(func=cmd_plan)
    register_intervals(sub)


def cmd_plan(args: argparse.Namespace) -> int:
    # on use: loads torch
    from torchmetal.plan.core import PlanOptions
    from torchmetal.plan.run import describe, plan_directory

    plan, seconds = plan_directory(args.source, args.output, options=PlanOptions(shots=args.shots), capture=args.capture)
    print(describe(plan, seconds) + f"\n-> {args.output}/plan.json, plan.png")
    return 0


def register_intervals(sub: argparse._SubParsersAction) -> None:
    """Add the ``intervals`` verb."""
    p = sub.add_parser("intervals", help="90 %% intervals of a material's flake statistics and estimated normals "
                                         "(refits with one shot left out) into its report",
                       description="After a fit: refit the material once per shot of its capture left out (the fit's "
                                   "choices fixed) and write the 90 % intervals of the flake statistics (where the "
                                   "material has flakes) and of the estimated normals (where the fit estimated them) "
                                   "into MATERIAL/material.json's report (uncertainty.leave_out). N shots: N refits.")
    p.add_argument("material", metavar="MATERIAL", help="material directory written by torchmetal fit")
    p.add_argument("capture", metavar="CAPTURE", help="the capture it was fitted to")
    p.add_argument("-q", "--quiet", action="store_true", help="no line per refit on stderr")
    p.set_defaults(func=cmd_intervals)


def cmd_intervals(args: argparse.Namespace) -> int:
    import sys
    import time

    # on use: loads torch
    from torchmetal.plan.intervals import describe, leave_out_intervals

    t0 = time.perf_counter()
    log = None if args.quiet else (lambda line: print(f"  {line}", file=sys.stderr, flush=True))
    entry = leave_out_intervals(args.material, args.capture, log=log)
    print(describe(entry) + f"\n-> {args.material}/material.json (uncertainty.leave_out) in {time.perf_counter() - t0:.1f} s")
    return 0
