"""The benchmark code path stays runnable (its numbers are for `codesign bench`, not for tests)."""
import json

import pytest

from codesign_mpm.reports.bench import Case, measure_batch, measure_forward


def test_forward_measurement_reports_throughput():
    record = measure_forward(Case("small", "float32"), repeats=2, frames=1)
    json.dumps(record)  # one JSON line per measurement
    assert record["measure"] == "forward"
    assert record["particles"] > 5000
    assert abs(record["substeps_per_frame"] * record["dt"] - 8e-3) < 1e-12
    assert record["particle_substeps_per_s"] > 0 and len(record["repeats"]) == 2


def test_batch_measurement_compares_one_batch_with_the_same_episodes_one_at_a_time():
    record = measure_batch(Case("tiny", "float32"), members=2, frames=1, repeats=1)
    json.dumps(record)
    assert record["members"] == 2 and record["particles_per_member"] > 500
    assert record["speedup"] > 0 and record["batch_particle_substeps_per_s"] > 0


def test_bench_compile_names_the_allowed_covers(cli):
    code, _, err = cli("bench", "compile", "--cover", "lava")
    assert code != 0 and "--cover 'lava': choose from none, sand, snow, clay, mud, water" in " ".join(err.replace("│", " ").split())


def test_the_profile_counts_a_substeps_kernel_launches_and_splits_its_time():
    """`codesign bench engine --profile --members 3`: a forward substep of the tiny scene is one
    launch (the fused substep; the state check once a frame), alone and for a batch of three, and
    the kernels' shares add up to one."""
    from codesign_mpm.reports.bench import run_profile_bench

    records = []
    run_profile_bench(["tiny"], "cpu", records.append, progress=False, members=3)
    (record,) = records
    assert "error" not in record, record.get("error")
    for forward in (record["forward"], record["batch"]):
        assert forward["kernels"]["_forward_substep"]["launches_per_substep"] == 1.0
        assert 1 <= forward["launches_per_substep"] < 3 and 0 <= forward["other_share"] < 1
        assert sum(k["share"] for k in forward["kernels"].values()) == pytest.approx(1.0, abs=0.01)
    assert record["batch"]["members"] == 3
    assert record["forward_backward"]["launches_per_substep"] > 3 * record["forward"]["launches_per_substep"]


def test_bench_engine_names_the_allowed_measures_and_archs(cli):
    code, _, err = cli("bench", "engine", "--measure", "speed")
    assert code != 0 and ("--measure 'speed': choose from forward, float64, dense, backward, batch, scatter, "
                          "adaptive, flip, contact") in " ".join(err.replace("│", " ").split())
    code, _, err = cli("bench", "engine", "--measure", "forward", "--segment-memory", "64")
    assert code != 0 and "--segment-memory sizes the backward measurement: add --measure backward" in \
        " ".join(err.replace("│", " ").split())
    code, _, err = cli("bench", "environments", "--arch", "opengl")
    assert code != 0 and "--arch 'opengl': choose from cpu, cuda" in " ".join(err.replace("│", " ").split())
