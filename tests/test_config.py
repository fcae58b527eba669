"""The fit's one configuration (torchmetal.config): checks, flat keywords, the CLI built from it, the tiled
fit's refusals from one place, the README's table kept in sync."""

import argparse
from pathlib import Path

import pytest

from torchmetal.config import FitConfig, add_fit_arguments, check_tiled, config_from_args, options_table
from torchmetal.errors import InputError

README = Path(__file__).resolve().parents[1] / "README.md"


def test_defaults_and_flat_keywords():
    c = FitConfig()
    assert c.choices.normals == c.choices.lobe == c.choices.light == "auto" and c.solver.scheme == "refine"
    d = FitConfig.of(normals="flat", observed_flakes=True, robust=None, max_iters=7, flakes="off", progress=True)
    assert d.choices.normals == "flat" and d.flakes.observed == "on" and d.solver.robust == "none"
    assert d.solver.max_iters == 7 and d.flakes.mode == "off" and d.progress
    assert FitConfig.of(d, lobe="ggx").choices.normals == "flat"  # a config with some keywords replaced
    flat = d.flat()
    assert flat["normals"] == "flat" and flat["observed_flakes"] == "on" and FitConfig.of(**flat) == d
    with pytest.raises(AttributeError):
        c.progress = True  # frozen


@pytest.mark.parametrize("kw, match", [({"normals": "bumpy"}, "normals: expected one of"),
                                       ({"light": "lamp"}, "light: expected one of"),
                                       ({"tol": -1.0}, "tol: expected a finite number"),
                                       ({"max_iters": 0}, "max_iters: expected an int"),
                                       ({"observed_flakes": "maybe"}, "observed_flakes: expected one of"),
                                       ({"colour": "red"}, "fit option: expected one of")])
def test_bad_options_are_refused_in_one_line(kw, match):
    with pytest.raises(InputError, match=match) as e:
        FitConfig.of(**kw)
    assert "\n" not in str(e.value)


def test_the_cli_arguments_come_from_the_config():
    p = argparse.ArgumentParser()
    add_fit_arguments(p)
    args = p.parse_args([])
    assert config_from_args(args, progress=False) == FitConfig()
    args = p.parse_args(["--normals", "relief", "--observed-flakes", "--max-iters", "5", "--robust", "none"])
    c = config_from_args(args, progress=True)
    assert c.choices.normals == "relief" and c.flakes.observed == "on" and c.solver.max_iters == 5 and c.solver.robust == "none"
    with pytest.raises(SystemExit):
        p.parse_args(["--lobe", "cook"])


def test_the_tiled_fit_refuses_from_one_place():
    check_tiled(FitConfig())  # the defaults are supported
    for kw in ({"normals": "estimate"}, {"lobe": "ggx"}, {"weights": "noise"}, {"light": "flash"},
               {"clipping": "pixel"}, {"scheme": "paper"}, {"robust": "huber"}, {"flakes": "on"}):
        with pytest.raises(InputError, match="with --tile"):
            check_tiled(FitConfig.of(**kw))


def test_the_readme_table_is_the_configs():
    text = README.read_text()
    start, end = "<!-- fit-options:start -->\n", "\n<!-- fit-options:end -->"
    assert start in text and end in text
    table = text[text.index(start) + len(start): text.index(end)]
    assert table == options_table(), "README's fit options are stale: paste torchmetal.config.options_table()"
    assert all(f"`--{name.replace('_', '-')}`" in table for name in FitConfig().flat() if name != "progress")
