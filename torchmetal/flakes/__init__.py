"""Metallic flakes: the statistical model, its deterministic field, detection and metrics."""

from torchmetal.flakes.field import FlakeField, flake_field, sparkle_render, sparkle_shading
from torchmetal.flakes.model import FlakeModel

__all__ = ["FlakeModel", "FlakeField", "flake_field", "sparkle_shading", "sparkle_render"]
