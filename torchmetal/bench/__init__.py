"""Benchmarks: run time against error, beside the paper's scheme (numpy/scipy) and per-pixel Adam.

``python -m torchmetal.bench [--quick] [--out DIR] [--sections a,b]`` or ``torchmetal bench``.
The baselines are importable on their own: :func:`paper_scheme_numpy`, :func:`adam_fit`.
"""

from torchmetal.bench.baselines import BaselineResult, adam_fit, paper_scheme_numpy

__all__ = ["BaselineResult", "paper_scheme_numpy", "adam_fit", "main"]


def main(argv: list[str] | None = None) -> int:
    # on use: imported with the package, __main__ would run twice under `python -m torchmetal.bench`
    from torchmetal.bench.__main__ import main as _main

    return _main(argv)
