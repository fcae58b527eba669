"""fit-many on the local process pool: identical to single fits, worker-count independent,
retries a killed worker, resumes without redoing, records failures."""

import csv

import pytest

from torchmetal.cli import main
from torchmetal.errors import InputError
from torchmetal.scale.fit_many import fit_many

from .helpers import kill_once_task, make_captures, material_fingerprint, never_task

FIT_ARGS = ["--flakes", "off", "--max-iters", "30"]


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    return make_captures(tmp_path_factory.mktemp("caps"))


@pytest.fixture(scope="module")
def single(captures, tmp_path_factory):
    """The three materials of three single ``torchmetal fit`` runs."""
    root = tmp_path_factory.mktemp("single")
    for cap in captures:
        assert main(["fit", str(cap), "-o", str(root / cap.name), *FIT_ARGS, "-q"]) == 0
    return {cap.name: material_fingerprint(root / cap.name) for cap in captures}


@pytest.mark.parametrize("workers", [1, 2])
def test_fit_many_equals_single_fits(captures, single, tmp_path, workers):
    bad = tmp_path / "broken"  # a capture fit rejects: failed once, its error kept, the others unaffected
    bad.mkdir()
    (bad / "capture.json").write_text("{not json")
    out = tmp_path / "out"
    recs = fit_many([*captures, bad], out, fit_args=FIT_ARGS, workers=workers, progress=False)
    assert [r.status for r in recs] == ["ok"] * 3 + ["failed"] and [r.attempts for r in recs] == [1] * 4
    assert "expected valid JSON" in recs[3].errors[0]  # bad input: not retried
    for cap in captures:  # bit-identical to a single fit, whatever the number of workers
        assert material_fingerprint(out / cap.name) == single[cap.name]
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["name"] for r in rows] == [c.name for c in captures] + ["broken"]
    assert [r["status"] for r in rows] == ["ok"] * 3 + ["failed"] and "expected valid JSON" in rows[3]["errors"]
    assert all(float(r["rmse"]) > 0 and float(r["time_s"]) > 0 for r in rows[:3])
    md = (out / "summary.md").read_text()
    assert "3 fitted" in md and "1 failed" in md and md.count("| cap") == 3


def test_killed_worker_is_retried_then_resume_redoes_nothing(captures, single, tmp_path):
    out = tmp_path / "out"
    recs = fit_many(captures, out, fit_args=FIT_ARGS, workers=2, progress=False, task=kill_once_task)
    by = {r.name: r for r in recs}
    assert all(r.status == "ok" for r in recs)
    assert by["cap1"].attempts == 2 and "worker process died" in by["cap1"].errors[0]
    for cap in captures:
        assert material_fingerprint(out / cap.name) == single[cap.name]
    stamp = {c.name: (out / c.name / "material.json").stat().st_mtime_ns for c in captures}
    again = fit_many(captures, out, fit_args=FIT_ARGS, workers=1, threads=2, progress=False, task=never_task)
    assert [r.status for r in again] == ["resumed"] * 3
    assert {c.name: (out / c.name / "material.json").stat().st_mtime_ns for c in captures} == stamp
    assert "3 done before (resumed)" in (out / "summary.md").read_text()
    # other fit options are another job: not taken as done
    other = fit_many(captures[:1], out, fit_args=[*FIT_ARGS, "--tol", "1e-5"], progress=False, task=never_task,
                     retries=0)
    assert other[0].status == "failed" and "task ran" in other[0].errors[0]


def test_cli_fit_many(captures, single, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["fit-many", *map(str, captures[:2]), "-o", str(out), "--workers", "2", "-q", *FIT_ARGS]) == 0
    assert "2 fitted" in capsys.readouterr().out
    assert material_fingerprint(out / "cap0") == single["cap0"]
    bad = tmp_path / "nothing"
    assert main(["fit-many", str(bad), "-o", str(out), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "1 of 1 captures failed" in err[0]


def test_bad_arguments(captures, tmp_path):
    with pytest.raises(InputError, match="distinct folder names"):
        fit_many([captures[0], captures[0]], tmp_path / "o", progress=False)
    with pytest.raises(InputError, match="engine"):
        fit_many(captures[:1], tmp_path / "o", engine="spark", progress=False)
    with pytest.raises(InputError, match="workers"):
        fit_many(captures[:1], tmp_path / "o", workers=0, progress=False)
