"""File I/O: images (sRGB, PNG/NPY/EXR) and capture directories (docs/design.md §2.1)."""

from torchmetal.io.capture import Capture, load_capture
from torchmetal.io.capture_save import save_capture
from torchmetal.io.images import linear_to_srgb, read_image, srgb_to_linear, write_image

__all__ = ["Capture", "load_capture", "save_capture", "read_image", "write_image", "srgb_to_linear", "linear_to_srgb"]
