"""One-line argument checks (kornia ``core/check`` style).

Each check raises :class:`~torchmetal.errors.InputError` (or the class passed as ``error``)
whose message names what was expected and what was found.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchmetal.errors import InputError, TorchmetalError


def check_tensor(x: object, name: str, error: type[TorchmetalError] = InputError) -> None:
    if not isinstance(x, torch.Tensor):
        raise error(f"{name}: expected a torch.Tensor, found {type(x).__name__}")


def check_shape(
    x: torch.Tensor, shape: Sequence[int | str], name: str, error: type[TorchmetalError] = InputError
) -> None:
    """Check ``x.shape`` against a pattern: ints are fixed, strings ("B", "H", "*") are free.

    A leading ``"*"`` allows any number of leading dims.
    """
    check_tensor(x, name, error)
    pattern = list(shape)
    dims = list(x.shape)
    if pattern and pattern[0] == "*":
        pattern = pattern[1:]
        dims = dims[len(dims) - len(pattern):] if len(dims) >= len(pattern) else None  # type: ignore[assignment]
    ok = dims is not None and len(dims) == len(pattern) and all(
        isinstance(p, str) or p == d for p, d in zip(pattern, dims)
    )
    if not ok:
        want = "(" + ", ".join(str(p) for p in shape) + ")"
        raise error(f"{name}: expected shape {want}, found {tuple(x.shape)}")


def check_float(x: torch.Tensor, name: str, error: type[TorchmetalError] = InputError) -> None:
    check_tensor(x, name, error)
    if not x.is_floating_point():
        raise error(f"{name}: expected a floating-point tensor, found dtype {x.dtype}")


def check_finite(x: torch.Tensor, name: str, error: type[TorchmetalError] = InputError) -> None:
    # a sum is finite only if every term is (NaN and ±Inf propagate): one cheap reduction on the
    # common path; the element-wise test runs only when it fails (or the sum overflowed)
    if not x.is_floating_point() or bool(torch.isfinite(x.sum())):
        return
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        n = int(bad.sum())
        kind = "NaN" if bool(torch.isnan(x).any()) else "Inf"
        raise error(f"{name}: expected finite values, found {n} non-finite ({kind}) of {x.numel()}")


def check_nonnegative(x: torch.Tensor, name: str, error: type[TorchmetalError] = InputError) -> None:
    if x.numel() and bool((x < 0).any()):
        raise error(f"{name}: expected values >= 0, found minimum {float(x.min()):.4g}")
