"""One exception family for everything torchmetal rejects.

Every error is raised at a boundary (file, CLI, public function) with the expected and the
actual value in a single line, so users never see a deep traceback from inside torch.
"""

from __future__ import annotations


class TorchmetalError(Exception):
    """Base class: a one-line, user-facing reason."""


class CaptureError(TorchmetalError):
    """A capture directory or capture tensors are malformed."""


class MaterialError(TorchmetalError):
    """A material directory or material parameters are malformed."""


class InputError(TorchmetalError, ValueError):
    """A tensor argument has the wrong shape, dtype or non-finite values."""


class FitError(TorchmetalError):
    """A fit could not run or produced non-finite values."""


class ExportError(TorchmetalError):
    """ONNX export or verification failed."""
