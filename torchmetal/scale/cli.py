"""``torchmetal fit-many CAPTURES... -o OUTDIR``: one ``fit`` per capture on a pool or on Ray.

Every capture is fitted by exactly ``torchmetal fit CAPTURE -o OUTDIR/<name> [fit options]``
run inside a worker, so fit-many takes every option ``fit`` has (they are copied from the
``fit`` sub-parser, including ones added later) and its materials are those of single fits.
argparse only at module top: the handler imports the rest.
"""

from __future__ import annotations

import argparse

_OWN = ("help", "capture", "output", "quiet")  # fit's own arguments that fit-many does not pass on


def _fit_options(fit_parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in fit_parser._actions if a.dest not in _OWN]


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fit-many`` verb to the sub-parsers ``sub`` (after ``fit``, whose options it copies)."""
    p = sub.add_parser("fit-many", help="fit many captures (one fit per capture) on a process pool or Ray",
                       description="Fit every capture with the same fit options; retries failed fits, skips "
                                   "materials already done, writes OUTDIR/summary.csv and summary.md.")
    p.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture directories (docs/design.md §2.1)")
    p.add_argument("-o", "--output", required=True, help="output folder: OUTDIR/<capture name>/ per material")
    p.add_argument("--engine", choices=["local", "ray"], default="local",
                   help="local: a process pool (no Ray needed); ray: Ray tasks (pip install torchmetal[ray])")
    p.add_argument("--address", default=None, help="Ray cluster address (default: start a local cluster)")
    p.add_argument("--workers", type=int, default=1, help="fits running at once (default: %(default)s)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads per fit (default: CPU cores / workers, at least 1)")
    p.add_argument("--retries", type=int, default=2, help="extra attempts after a failed fit (default: %(default)s)")
    p.add_argument("--no-resume", action="store_true", help="refit captures whose material is already done")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    fit = sub.choices.get("fit")
    group = p.add_argument_group("fit options (passed to every fit)")
    fit_actions = _fit_options(fit) if fit is not None else []
    for action in fit_actions:
        group._add_action(action)  # the same Action objects: argparse's own ``parents`` mechanism
    p.set_defaults(func=cmd_fit_many, fit_actions=fit_actions)


def fit_argv(args: argparse.Namespace, actions: list[argparse.Action]) -> list[str]:
    """The ``fit`` command-line options that reproduce ``args`` (only those off their default)."""
    out: list[str] = []
    for a in actions:
        value = getattr(args, a.dest, a.default)
        if value == a.default:
            continue
        flag = a.option_strings[-1]
        if a.nargs == 0:  # store_true / store_false / store_const
            out.append(flag)
        elif isinstance(value, (list, tuple)):
            out += [flag, *map(str, value)]
        else:
            out += [flag, str(value)]
    return out


def cmd_fit_many(args: argparse.Namespace) -> int:
    import os

    # on use: a verb module imports only argparse at the top (CLI start-up)
    from torchmetal.errors import InputError
    from torchmetal.scale.fit_many import fit_many

    if args.workers < 1:
        raise InputError(f"--workers: expected an int >= 1, found {args.workers}")
    if args.threads is not None and args.threads < 1:
        raise InputError(f"--threads: expected an int >= 1, found {args.threads}")
    threads = args.threads or max(1, (os.cpu_count() or 1) // args.workers)
    records = fit_many(
        args.captures, args.output, fit_args=fit_argv(args, args.fit_actions), engine=args.engine,
        workers=args.workers, address=args.address, retries=args.retries, threads=threads,
        progress=not args.quiet, resume=not args.no_resume,
    )
    failed = [r for r in records if r.status == "failed"]
    done = sum(r.status == "ok" for r in records)
    print(f"fit-many: {done} fitted, {sum(r.status == 'resumed' for r in records)} done before, {len(failed)} failed "
          f"-> {args.output}/summary.md")
    if failed:
        print(f"torchmetal fit-many: error: {len(failed)} of {len(records)} captures failed "
              f"(first: {failed[0].name}: {failed[0].errors[-1] if failed[0].errors else 'unknown'})",
              file=__import__("sys").stderr)
        return 1
    return 0
