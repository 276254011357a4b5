"""The quick sizes of `codesign bench accuracy` and `codesign bench stability` run and write their
reports. The quick sizes are tiny, but each setting starts its own process and compiles (or loads)
its kernels (a backward pass: minutes cold). A small subset (about 20 s warm) runs in the default
selection; the full quick reports are marked `report` and left out of it (every cover material's
backward kernels compile for about 20 minutes cold): run them with `pytest -m report`."""
import json
import math

import numpy as np
import pytest

from codesign_mpm.reports.accuracy import PROBLEMS, run_accuracy_bench
from codesign_mpm.reports.documents import pareto_front, write_accuracy_report, write_stability_report
from codesign_mpm.reports.machine import machine_description
from codesign_mpm.reports.stability import CASES, passed, run_stability_bench


def test_pareto_front_keeps_only_the_unbeaten_settings():
    points = [(1.0, 0.5), (2.0, 0.1), (3.0, 0.2), (0.5, 0.9), (4.0, 0.01)]
    assert sorted(pareto_front(points)) == [0, 1, 3, 4]


def check_accuracy_rows(rows, problems):
    assert {r["problem"] for r in rows} == set(problems)
    for r in rows:
        json.dumps(r)
        assert "failed" not in r, r
        assert math.isfinite(r["error"]) and r["wall_s"] > 0 and r["peak_rss_mb"] > 0
        assert np.isfinite(r["value"]).all()
    for name in problems:  # a converged answer is the one reference setting's; an analytic one has none
        refs = [r for r in rows if r["problem"] == name and r["reference"]]
        assert len(refs) == (0 if all("exact" in r for r in rows if r["problem"] == name) else 1)


def test_quick_accuracy_of_the_bar_writes_a_report(tmp_path):
    rows = run_accuracy_bench(["bar"], "quick", lambda r: None)
    check_accuracy_rows(rows, ["bar"])
    assert max(r["error"] for r in rows) < 0.05  # the frequency is within 5% even at dx 1/20
    doc = write_accuracy_report(rows, tmp_path)
    text = doc.read_text()
    assert "## Quality presets" in text and "![bar" in text and "**yes**" in text
    assert f"{len(rows)} records measured on {machine_description()}" in text  # each record names its machine
    assert (tmp_path / "images" / "accuracy_bar.png").stat().st_size > 1000
    assert len((tmp_path / "data" / "accuracy-quick.jsonl").read_text().splitlines()) == len(rows)


@pytest.mark.slow
def test_quick_gradient_accuracy_matches_finite_differences_and_checkpoints_change_nothing():
    grad = run_accuracy_bench(["gradient"], "quick", lambda r: None, isolate=False)  # the bar's test runs isolated
    check_accuracy_rows(grad, ["gradient"])
    assert all(r["fd_error_actions"] < 1e-3 and r["fd_error_stiffness"] < 1e-3 for r in grad
               if r["dtype"] == "float64")  # float64 gradients match float64 finite differences
    checkpointed = next(r for r in grad if r["checkpoint_every"] == 1)
    plain = next(r for r in grad if r["checkpoint_every"] is None and r["cfl"] == 0.4)
    np.testing.assert_allclose(checkpointed["value"], plain["value"], rtol=1e-9, atol=1e-12)


@pytest.mark.slow
@pytest.mark.report
def test_quick_accuracy_report_of_every_problem(tmp_path):
    rows = run_accuracy_bench(list(PROBLEMS), "quick", lambda r: None)
    check_accuracy_rows(rows, list(PROBLEMS))
    text = write_accuracy_report(rows, tmp_path).read_text()
    for name in PROBLEMS:
        assert f"(`{name}`)" in text
        assert (tmp_path / "images" / f"accuracy_{name}.png").exists()


def check_stability_rows(rows):
    for r in rows:
        json.dumps(r)
        # an admissible case runs its whole horizon finite; an inadmissible one may stop with a clear
        # error; never a NaN, never another exception; and the integrator never creates energy
        assert passed(r), r
        if r["outcome"] == "finite":
            assert all(math.isfinite(r[k]) for k in ("max_speed", "min_J", "max_J", "energy_drift",
                                                     "grad_actions_norm", "grad_x0_norm"))
            assert r["energy_excess"] <= 1e-3, r


def test_quick_stability_of_two_cases_writes_a_report(tmp_path):
    cases = ["near_inverted", "leaving_domain"]
    rows = run_stability_bench(cases, "quick", lambda r: None, isolate=False)
    assert [r["case"] for r in rows] == cases
    check_stability_rows(rows)
    text = write_stability_report(rows, tmp_path).read_text()
    assert all(f"## `{c}`" in text for c in cases)
    assert f"2 records measured on {machine_description()}" in text  # each record names its machine


@pytest.mark.slow
@pytest.mark.report
def test_quick_stability_of_every_case(tmp_path):
    rows = run_stability_bench(list(CASES), "quick", lambda r: None)
    check_stability_rows(rows)
    write_stability_report(rows, tmp_path)
