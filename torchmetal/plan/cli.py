"""``torchmetal plan CAPTURE_OR_MATERIAL [-n K] -o DIR`` (docs/design.md §2.5): the next K photos to take.

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


def cmd_plan(args: argparse.Namespace) -> int:
    # on use: loads torch
    from torchmetal.plan.core import PlanOptions
    from torchmetal.plan.run import describe, plan_directory

    plan, seconds = plan_directory(args.source, args.output, options=PlanOptions(shots=args.shots), capture=args.capture)
    print(describe(plan, seconds) + f"\n-> {args.output}/plan.json, plan.png")
    return 0
