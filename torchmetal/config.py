"""The fit's options: one frozen, nested :class:`FitConfig`, the single source of their names, defaults,
allowed values and help.

It builds ``torchmetal fit``'s arguments and help (:func:`add_fit_arguments`; ``fit-many`` copies them), the
README's option table (:func:`options_table`; tests/test_config.py keeps the README in sync), the options
:func:`~torchmetal.pipeline.fit_material` takes, and what the tiled fit supports (``tiled`` in each option's
metadata; :func:`check_tiled` refuses the rest from this one place).

An option's metadata: ``choices`` (allowed values, or None for numbers), ``help`` (one line), ``tiled`` (the
values a tiled fit supports; None: any). The groups: the automatic choices (each ``auto`` by default: chosen on
shots the fit left out, docs/design.md §4), the solver, the flake stage.

Imports nothing heavy: the CLI builds its parser from it before torch is loaded.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from torchmetal.errors import InputError


def option(default: Any, help: str, choices: tuple | None = None, tiled: tuple | None = None, flag: str | None = None) -> Any:
    """A config field with its metadata (module docstring); ``flag``: its CLI and keyword name where it differs."""
    return field(default=default, metadata={"help": help, "choices": choices, "tiled": tiled, "flag": flag})


@dataclass(frozen=True)
class ChoiceOptions:
    """The automatic choices: ``auto`` decides each on shots the fit left out (docs/design.md §4)."""

    registration: str = option("auto", "the shots as captured (off), or each moved back by its measured shift against "
                                       "the others (shift: phone photos rectified from markers)",
                               ("auto", "off", "shift"), tiled=("auto", "off"))
    clipping: str = option("auto", "how an observation with a clipped channel is read: channel keeps its other "
                                   "channels (a linear sensor), pixel drops all three (a phone's processing)",
                           ("auto", "channel", "pixel"), tiled=("auto", "channel"))
    normals: str = option("auto", "given: the capture's normals.npy (auto keeps it, flat or not); flat; estimate: "
                                  "photometric stereo; relief: an embossing's high-passed height field",
                          ("auto", "given", "flat", "estimate", "relief"), tiled=("auto", "given"))
    light: str = option("auto", "the capture's lights (off), the flash's one move of every light (flash), per-shot "
                                "positions, the flash's falloff, or falloff and per-shot gains",
                        ("auto", "off", "flash", "positions", "falloff", "gains"), tiled=("auto", "off"))
    lobe: str = option("auto", "the specular lobe: phong (the paper's), blinn, ggx (microfacet with Fresnel)",
                       ("auto", "phong", "blinn", "ggx"), tiled=("auto", "phong"))
    weights: str = option("auto", "least-squares weights: uniform, or noise (each observation by the inverse of its "
                                  "expected noise variance)", ("auto", "uniform", "noise"), tiled=("auto", "uniform"))
    specular: str = option("auto", "the specular structure: global, clustered, maps (gloss maps), none",
                           ("auto", "global", "clustered", "maps", "none"))


@dataclass(frozen=True)
class SolverOptions:
    """The Phong fit's scheme and stopping rules."""

    scheme: str = option("refine", "refine: the paper's scheme, then the joint refinement; paper: the paper's alone",
                         ("refine", "paper"), tiled=("refine",))
    tol: float = option(1e-6, "relative error change that stops the fit")
    max_iters: int = option(100, "iteration cap per stage")
    robust: str = option("auto", "IRLS weights: auto is least squares, Huber for the flake statistics once glints "
                                 "are found", ("auto", "none", "huber", "cauchy"), tiled=("auto", "none"))


@dataclass(frozen=True)
class FlakeOptions:
    """The flake stage."""

    mode: str = option("auto", "a flake model: auto keeps it where left-out shots' sparkle statistics (MD) are no "
                                 "further from the photos with it; on: whenever detections exceed noise",
                       ("auto", "on", "off"), tiled=("auto", "off"), flag="flakes")
    observed: str = option("auto", "keep the flakes the shots saw where they are, the statistical field filling "
                                   "the rest", ("auto", "on", "off"), flag="observed_flakes")
    seed: int = option(0, "seed of the flake field")


@dataclass(frozen=True)
class FitConfig:
    """Every option of :func:`~torchmetal.pipeline.fit_material`, checked on construction (a one-line
    :class:`~torchmetal.errors.InputError` otherwise). Build it from flat keywords with :meth:`of`."""

    choices: ChoiceOptions = field(default_factory=ChoiceOptions)
    solver: SolverOptions = field(default_factory=SolverOptions)
    flakes: FlakeOptions = field(default_factory=FlakeOptions)
    progress: bool = False

    def __post_init__(self) -> None:
        for group, f in _fields():
            value = getattr(getattr(self, group), f.name)
            name = _flag(f)
            if f.metadata["choices"] is not None and value not in f.metadata["choices"]:
                raise InputError(f"{name}: expected one of {list(f.metadata['choices'])}, found {value!r}")
        tol, iters = self.solver.tol, self.solver.max_iters
        if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
            raise InputError(f"tol: expected a finite number > 0, found {tol!r}")
        if isinstance(iters, bool) or not isinstance(iters, int) or iters < 1:
            raise InputError(f"max_iters: expected an int >= 1, found {iters!r}")
        if isinstance(self.flakes.seed, bool) or not isinstance(self.flakes.seed, int):
            raise InputError(f"seed: expected an int, found {self.flakes.seed!r}")

    @classmethod
    def of(cls, config: FitConfig | None = None, **options: Any) -> FitConfig:
        """``config`` (default: the defaults) with the flat keyword ``options`` replaced (their names are the CLI's,
        ``-`` as ``_``: ``normals="flat"``, ``observed_flakes="on"``, ``max_iters=50``); unknown names are refused."""
        base = config or cls()
        where = {_flag(f): (group, f.name) for group, f in _fields()}
        groups: dict[str, dict] = {}
        top = {}
        for key, value in options.items():
            if key == "progress":
                top["progress"] = bool(value)
                continue
            if key not in where:
                raise InputError(f"fit option: expected one of {sorted([*where, 'progress'])}, found {key!r}")
            group, name = where[key]
            groups.setdefault(group, {})[name] = _normal(key, value)
        parts = {g: dataclasses.replace(getattr(base, g), **kw) for g, kw in groups.items()}
        return dataclasses.replace(base, **parts, **top)

    def flat(self) -> dict[str, Any]:
        """The options as flat keywords (:meth:`of`'s names)."""
        return {_flag(f): getattr(getattr(self, g), f.name) for g, f in _fields()} | {"progress": self.progress}

    def fit_kwargs(self) -> dict:
        """:func:`~torchmetal.fit.fit_phong` arguments every fit of the run shares (``robust`` and ``lobe`` aside)."""
        s, c = self.solver, self.choices
        return dict(scheme=s.scheme, specular=c.specular, tol=s.tol, max_iters=s.max_iters, progress=self.progress,
                    weights=c.weights)


def _fields() -> list[tuple[str, dataclasses.Field]]:
    """(group, field) of every option, in the order they are declared."""
    out = []
    for g in ("choices", "solver", "flakes"):
        typ = {"choices": ChoiceOptions, "solver": SolverOptions, "flakes": FlakeOptions}[g]
        out += [(g, f) for f in dataclasses.fields(typ)]
    return out


def _flag(f: dataclasses.Field) -> str:
    return f.metadata.get("flag") or f.name


def _normal(key: str, value: Any) -> Any:
    """A keyword's value in the config's form: robust None is "none"; observed flakes True/False are "on"/"off"."""
    if key == "robust" and value is None:
        return "none"
    if key == "observed_flakes" and isinstance(value, bool):
        return "on" if value else "off"
    return value


def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """``fit``'s option arguments, one per config option, with their choices, defaults and one-line help."""
    for _, f in _fields():
        name = _flag(f)
        kw: dict[str, Any] = {"default": f.default, "help": f"{f.metadata['help']} (default: %(default)s)"}
        if f.metadata["choices"] is not None:
            kw["choices"] = list(f.metadata["choices"])
        else:
            kw["type"] = type(f.default)
        if name == "observed_flakes":
            kw |= {"nargs": "?", "const": "on"}  # a bare flag: on
        parser.add_argument("--" + name.replace("_", "-"), **kw)


def config_from_args(args: argparse.Namespace, progress: bool) -> FitConfig:
    """The :class:`FitConfig` of parsed ``fit`` arguments."""
    return FitConfig.of(progress=progress, **{_flag(f): getattr(args, _flag(f)) for _, f in _fields()})


def check_tiled(config: FitConfig) -> None:
    """Refuse, in one line, an option value the tiled fit does not support (each option's ``tiled`` values)."""
    for group, f in _fields():
        allowed = f.metadata["tiled"]
        value = getattr(getattr(config, group), f.name)
        if allowed is not None and value not in allowed:
            raise InputError(f"--{_flag(f).replace('_', '-')} {value}: expected one of {list(allowed)} with --tile "
                             "(the tiled fit's model: docs/scale.md)")


def options_table() -> str:
    """The README's table of ``fit``'s options (markdown), generated from the config."""
    rows = ["| option | values (default first) | what it sets | tiled fits |", "| --- | --- | --- | --- |"]
    for _, f in _fields():
        name = "--" + _flag(f).replace("_", "-")
        choices = f.metadata["choices"]
        values = f"`{f.default}`" if choices is None else ", ".join(f"`{v}`" for v in (f.default, *[c for c in choices if c != f.default]))
        tiled = "any" if f.metadata["tiled"] is None else ", ".join(f"`{v}`" for v in f.metadata["tiled"])
        rows.append(f"| `{name}` | {values} | {f.metadata['help']} | {tiled} |")
    return "\n".join(rows)


__all__ = ["ChoiceOptions", "FitConfig", "FlakeOptions", "SolverOptions", "add_fit_arguments", "check_tiled",
           "config_from_args", "options_table"]
