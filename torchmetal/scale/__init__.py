"""Scale out: many captures on a process pool or Ray (``fit_many``), and tiled fits of captures
larger than memory (``fit_tiled``). See docs/scale.md."""
