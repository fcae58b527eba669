"""onnx_kinds: one material per kind, exported, timed, profiled where over the target."""

from __future__ import annotations

import torch

from torchmetal.bench import kinds


def test_every_kind_builds_what_it_says():
    for name in kinds.kinds():
        m = kinds.make_material(name, 8)
        assert ("bumpy" in name) == (m.normals is not None), name
        if m.normals is not None:
            assert torch.allclose(m.normals.norm(dim=0), torch.ones(8, 8), atol=1e-5)
        assert ("clustered" in name) == m.clustered, name
        assert ("flakes" in name) == (m.flakes is not None), name
        assert ("observed" in name) == (getattr(m, "observed_flakes", None) is not None), name
        assert ("gloss" in name) == (getattr(m, "gloss_s", None) is not None), name
        assert m.lobe == ("blinn" if "blinn" in name else "ggx" if "ggx" in name else "phong")
        assert ("one α" in name) == bool((m.alpha == m.alpha[0]).all()), name


def test_run_kind_times_and_profiles(monkeypatch):
    monkeypatch.setattr(kinds, "TARGET_MS", 0.0)  # every kind "misses": the profiler runs
    r = kinds.run_kind("bumpy · clustered · flakes", 16, repeats=2)
    assert r["file_bytes"] > 0 and r["export_s"] > 0 and 0 < r["ms_min"] <= r["ms_median"]
    assert r["cpu_ms"] > 0 and r["load_1min"] >= 0
    assert r["top_ops"] and all(ms >= 0 for _, ms in r["top_ops"]) and sum(ms for _, ms in r["top_ops"]) > 0
    md = kinds.markdown([r, {"kind": "x", "error": "boom"}])
    assert "| bumpy · clustered · flakes |" in md and "| no |" in md and "boom" in md


def test_main_rejects_unknown_kind(tmp_path):
    assert kinds.main(["nope", "8", "1", str(tmp_path / "o.json")]) == 2
