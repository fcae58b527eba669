"""The core of the coating's own highlight (torchmetal.flakes.estimate.lobe_core), left out of the screen and the
null test: a sharp lobe of the wrong shape on curved normals is not taken for glints."""

import pytest
import torch

from tests.fit.helpers import synth
from torchmetal.fit import fit_phong
from torchmetal.flakes.estimate import lobe_core, prescreen
from torchmetal.flakes.estimate.results import Particles
from torchmetal.io.capture import load_capture
from torchmetal.synth.zoo import ci_scenes, make_case


@pytest.fixture(scope="module")
def shiny():
    cap = synth(size=48, shots=8, seed=3).capture
    return cap, fit_phong(cap)


def _rendered_peak(fit, cap, k: int) -> tuple[int, int]:
    from dataclasses import replace

    spec = replace(fit, texture=torch.zeros_like(fit.texture)).render(cap.lights[k:k + 1], cap.intensities[k:k + 1],
                                                                     cap.cameras[k:k + 1])[0].sum(0)
    i = int(spec.argmax())
    return divmod(i, spec.shape[-1])


def test_core_is_the_highlight_centre_and_nothing_far_from_it(shiny):
    cap, fit = shiny
    for k in range(cap.num_shots):
        r, c = _rendered_peak(fit, cap, k)
        far_r, far_c = (0 if r > 24 else 47), (0 if c > 24 else 47)
        core = lobe_core.lobe_core_at(fit, cap, torch.tensor([k, k]), torch.tensor([r, far_r]), torch.tensor([c, far_c]))
        assert bool(core[0]), (k, r, c)
        if float(fit.alpha.min()) > 20:  # a lobe narrower than the sample
            assert not bool(core[1]), (k, far_r, far_c)


def test_no_specular_no_core(shiny):
    from dataclasses import replace

    cap, fit = shiny
    dull = replace(fit, s=torch.zeros_like(fit.s))
    assert not lobe_core.lobe_core_at(dull, cap, torch.zeros(5, dtype=torch.long), torch.arange(5), torch.arange(5)).any()
    assert lobe_core.lobe_core_at(fit, cap, torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long),
                                  torch.zeros(0, dtype=torch.long)).shape == (0,)


def test_drop_core_keeps_the_others(shiny):
    cap, fit = shiny
    r, c = _rendered_peak(fit, cap, 0)
    p = Particles.empty(cap.images.device)
    fields = {f: getattr(p, f) for f in p.__dataclass_fields__}
    n = 2
    for f, v in fields.items():
        fields[f] = torch.zeros((n,) + tuple(v.shape[1:]), dtype=v.dtype)
    fields["cy"] = torch.tensor([r + 0.5, 0.5], dtype=fields["cy"].dtype)
    fields["cx"] = torch.tensor([c + 0.5, 0.5], dtype=fields["cx"].dtype)
    kept, dropped = lobe_core.drop_core(fit, cap, type(p)(**fields))
    assert dropped >= 1 and len(kept) == n - dropped


@pytest.fixture(scope="module")
def sphere(tmp_path_factory):
    sc = next(s for s in ci_scenes() if s.name == "sphere_sharp72")
    case = make_case(sc, tmp_path_factory.mktemp("sphere"))
    cap = load_capture(case.capture_dir)
    return cap, fit_phong(cap)


def test_sharp_sphere_reproduces_the_false_pass_without_the_core(sphere, monkeypatch):
    """The zoo's sphere_sharp72 (GGX truth, α 700, 66 directional lights, 16-bit): counted everywhere, its
    highlight cores pass the screen; left out, the screen rejects it before any detection."""
    cap, fit = sphere
    passed, counts = prescreen.screen_fit(fit, cap)
    assert not passed, counts
    monkeypatch.setattr(prescreen, "LOG_CORE", float("inf"))  # no pixel-shot is in a core
    passed, counts = prescreen.screen_fit(fit, cap)
    assert passed, counts


def test_sharp_sphere_gets_no_flakes_and_stops_at_the_screen(sphere):
    from torchmetal.pipeline import fit_material

    cap, _ = sphere
    res = fit_material(cap)
    assert res.material.flakes is None
    flakes = res.report["flakes"]
    assert "screen" in flakes and "particles" not in flakes  # no detection ran
