"""FlakeModel: a model is checked where it is made, so every material renders and exports."""

import math

import pytest
import torch

from torchmetal.errors import MaterialError
from torchmetal.flakes.model import MAX_COLOR, FlakeModel
from torchmetal.flakes.model.field import colour_factor

EYE = ((0.01, 0.0, 0.0), (0.0, 0.01, 0.0), (0.0, 0.0, 0.01))


@pytest.mark.parametrize("cov, what", [
    (((1e36, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "entries"),  # seen: a foil disc's false flake model
    (((math.nan, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "finite"),
    (((1.0, 0.5, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "symmetric"),
    (((1.0, 2.0, 0.0), (2.0, 1.0, 0.0), (0.0, 0.0, 1.0)), "positive semi-definite"),
])
def test_bad_covariance_is_refused(cov, what):
    with pytest.raises(MaterialError, match=what):
        FlakeModel(density=0.01, color_cov=cov)


def test_implausible_colour_is_refused():
    with pytest.raises(MaterialError, match="color_mean"):
        FlakeModel(density=0.01, color_mean=(1.5e6, 0.5, 0.5))
    FlakeModel(density=0.01, color_mean=(MAX_COLOR, 0.5, 0.5))  # the bound itself is allowed


def test_colour_factor_of_a_rank_deficient_covariance():
    """A PSD-to-rounding covariance (rank 1: grey flakes of varying brightness) factors without error."""
    v = torch.tensor([0.3, 0.3, 0.3], dtype=torch.float64)
    cov = torch.outer(v, v) - 1e-18 * torch.eye(3, dtype=torch.float64)
    m = FlakeModel(density=0.01, color_cov=tuple(tuple(r) for r in cov.tolist()))
    L = colour_factor(m.color_cov)
    assert torch.isfinite(L).all()
    assert torch.allclose(L @ L.T, torch.outer(v, v), atol=1e-9)


def test_colour_factor_reproduces_a_full_covariance():
    cov = torch.tensor([[0.04, 0.01, 0.0], [0.01, 0.03, 0.005], [0.0, 0.005, 0.02]], dtype=torch.float64)
    L = colour_factor(cov.tolist())
    assert torch.allclose(L @ L.T, cov, atol=1e-12)
    FlakeModel(density=0.01, color_cov=EYE)  # a plain model is accepted
