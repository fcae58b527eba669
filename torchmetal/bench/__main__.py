"""``python -m torchmetal.bench`` / ``torchmetal bench``: run time against error (see runner)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from torchmetal.bench.plans import full_plan, quick_plan
from torchmetal.bench.runner import SECTIONS, default_data_dir, run


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="torchmetal bench",
        description="Benchmark run time against error: torchmetal beside a numpy/scipy implementation of the "
        "paper's scheme and a per-pixel Adam fit, on the same synthetic captures; plus capture loading, "
        "skip evidence, flake detection, ONNX frame time and real-data leave-one-out PSNR.",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="tiny sizes, one child process per section (CI, < 60 s)")
    mode.add_argument("--full", action="store_true", help="the full sweep, 256² to 2048², 4 to 32 shots (default)")
    p.add_argument("--out", default="bench-results", help="output directory (default: %(default)s)")
    p.add_argument("--sections", default=",".join(SECTIONS),
                   help=f"comma-separated subset of {','.join(SECTIONS)} (default: all)")
    p.add_argument("--data", default=None, help="directory with real captures (default: $TORCHMETAL_SHARED_DATA, "
                   "else ../shared/data beside the checkout, when present)")
    p.add_argument("--timeout", type=float, default=None, help="seconds before a child process is stopped")
    p.add_argument("--isolate", action=argparse.BooleanOptionalAction, default=None,
                   help="one child process per run (default: on for --full, off for --quick)")
    p.add_argument("--threads", type=int, default=None,
                   help="intra-op threads of every run (default: torch's default; 1 avoids OpenMP stalls on a busy machine)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the final location")
    return p


def _stop(signum, frame):  # SIGTERM → normal exit, so temporary captures and children are cleaned up
    raise SystemExit(128 + signum)


def _importable(module: str) -> bool:
    import importlib.util

    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    missing = [name for name, mod in (("scipy", "scipy.optimize"), ("scikit-image", "skimage")) if not _importable(mod)]
    if missing:  # the numpy/scipy paper baseline, the zoo's photo textures
        print(f"torchmetal bench: error: expected scipy and scikit-image (pip install 'torchmetal[bench]'), found "
              f"{' and '.join(missing)} missing", file=sys.stderr)
        return 2
    sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    bad = [s for s in sections if s not in SECTIONS]
    if bad:
        print(f"torchmetal bench: error: --sections: expected names from {','.join(SECTIONS)}, found {','.join(bad)}",
              file=sys.stderr)
        return 2
    plan = quick_plan() if args.quick else full_plan()
    plan.full_rows = bool(args.full)
    if args.timeout is not None:
        plan.timeout_s = args.timeout
    if args.isolate is not None:
        plan.isolate = args.isolate
    if args.threads is not None:
        if args.threads < 1:
            print(f"torchmetal bench: error: --threads: expected an int >= 1, found {args.threads}", file=sys.stderr)
            return 2
        plan.threads = args.threads
    data = Path(args.data) if args.data else default_data_dir()
    main_thread = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGTERM, _stop) if main_thread else None
    try:
        run(plan, Path(args.out), sections, data_dir=data, verbose=not args.quiet)
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, old)
    if args.quiet:
        print(Path(args.out) / "results.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
