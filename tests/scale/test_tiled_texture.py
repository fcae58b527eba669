"""Tile-by-tile median and inpainting equal the whole-image ones."""

import numpy as np
import pytest
import torch

from torchmetal.errors import FitError
from torchmetal.fit.refine import fill_unobserved
from torchmetal.scale.tiled import tile_grid
from torchmetal.scale.tiled_texture import SeenStats, fill_tiles


@pytest.mark.parametrize("n", [1, 2, 999, 1000])
def test_radix_median_is_torchs_median(n):
    g = torch.Generator().manual_seed(n)
    vals = torch.rand(3, n, generator=g) ** 6 * 1e3  # spread over many binary exponents
    vals[1, : n // 3] = 0.0  # not observed: left out
    vals[2, 1::2] = vals[2, 0::2][: vals[2, 1::2].numel()]  # ties
    tiles = list(vals.split(max(1, n // 7), dim=1))
    st = SeenStats()
    for t in tiles:
        st.add(t)
    med = st.median(lambda bucket: (SeenStats.low_bits(t, bucket) for t in tiles))
    for c in range(3):
        v = vals[c][vals[c] > 0]
        assert med[c] == (v.median() if v.numel() else 0.0)


def test_fill_by_tiles_equals_whole_image():
    g = torch.Generator().manual_seed(0)
    h, w = 150, 170
    tex = torch.rand(3, h, w, generator=g) - 0.1
    bad = torch.zeros(3, h, w, dtype=torch.bool)
    bad[:, 60:90, 20:100] = True  # a blob across tile borders
    bad[1, 5:8, 160:170] = True
    bad[:, torch.rand(h, w, generator=g) > 0.97] = True
    want = fill_unobserved(tex, bad).clamp_min(0.0)
    out = np.zeros((h, w, 3), np.float32)
    fill_tiles(tex.permute(1, 2, 0).numpy(), bad.permute(1, 2, 0).numpy(), tile_grid(h, w, 32), out)
    assert torch.equal(torch.from_numpy(out).permute(2, 0, 1), want)


def test_fill_beyond_reach_is_refused():
    tex = torch.rand(3, 200, 200)
    bad = torch.zeros(3, 200, 200, dtype=torch.bool)
    bad[:, :, :150] = True  # 150 px from any observed texel
    with pytest.raises(FitError, match="farther than 64 px"):
        fill_tiles(tex.permute(1, 2, 0).numpy(), bad.permute(1, 2, 0).numpy(), tile_grid(200, 200, 50),
                   np.zeros((200, 200, 3), np.float32))
