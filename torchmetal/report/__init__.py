"""Figures and numbers that show what a fit did: shared by ``torchmetal demo`` and the notebooks.

Everything here reads results, it never fits. The helpers take plain tensors (linear RGB
``(3, H, W)`` images, per-channel ``(3,)`` terms) and a matplotlib ``Axes``, so a notebook can
draw one panel at a time; :func:`report_figure` puts them together into the demo's one-page
report:

========================  =======================================================================
panel                     what it shows
========================  =======================================================================
input shots               a few of the photos the fit saw (same exposure for all)
fitted texture            the diffuse texture d(p) (and the truth beside it when known)
specular lobe             s·max(r·v, 0)^α per channel against the angle between r and v, over
                          the evidence (photo − fitted diffuse)/E sampled from the shots
detected flakes           the flake residual (photo − Phong render) of one shot, with the
                          ellipses of the particles detected in it
re-render vs photo        the fitted material rendered for a shot, beside the photo
error map                 |render − photo| per pixel, in units of the photo's peak
========================  =======================================================================

Display convention: images are linear radiance; for viewing they are scaled so that a high
percentile of the *reference* maps to 1, clipped, and sRGB-encoded. Photo and render always share
one scale, so brightness differences in the figure are real.

PSNR in the titles is :func:`torchmetal.metrics.psnr` (linear values clipped to [0, 1], peak 1),
the same number the demo's metrics report.
"""

from torchmetal.metrics import psnr  # re-exported: the notebooks import it from here
from torchmetal.report.page import report_figure
from torchmetal.report.panels import (
    exposure_for,
    lobe_samples,
    particle_ellipses,
    plot_error,
    plot_flakes,
    plot_image,
    plot_lobe,
    plot_shots,
    to_display,
)

__all__ = [
    "psnr",
    "exposure_for",
    "to_display",
    "plot_image",
    "plot_shots",
    "plot_lobe",
    "lobe_samples",
    "plot_flakes",
    "plot_error",
    "particle_ellipses",
    "report_figure",
]
