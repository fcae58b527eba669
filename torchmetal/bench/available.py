"""What a benchmark task does when a stage it needs is missing.

A task imports its stages through :func:`need`; a stage that is not importable yet, or lacks the
expected name, raises :class:`NotAvailable`, which :mod:`torchmetal.bench.worker` reports as
``{"not_available": reason}`` instead of a failure.
"""

from __future__ import annotations


class NotAvailable(Exception):
    """A stage this task needs cannot be imported or does not have the expected API."""


def need(module: str, *names: str):
    """Import ``names`` from ``module`` or raise :class:`NotAvailable` with the reason."""
    import importlib

    try:
        mod = importlib.import_module(module)
    except Exception as e:  # ImportError, or a half-written module failing at import
        raise NotAvailable(f"{module} not importable ({type(e).__name__}: {e})") from None
    out = []
    for n in names:
        if not hasattr(mod, n):
            raise NotAvailable(f"{module}.{n} does not exist")
        out.append(getattr(mod, n))
    return out[0] if len(out) == 1 else out
