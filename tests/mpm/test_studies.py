"""Every shipped study (recipes/studies/) runs end to end at its tiny scale: its arms or its
analysis, its table or findings, its charts. The real runs are not tests (docs/studies.md)."""
import csv
import json
import math

import pytest

from codesign.recipe import RECIPES_DIR
from codesign.study import load_study, run_study

pytestmark = pytest.mark.slow  # the ocean's differentiable kernels compile for minutes on a cold cache

SHIPPED = sorted(p.stem for p in (RECIPES_DIR / "studies").glob("*.yaml"))


@pytest.mark.parametrize("name", SHIPPED)
def test_each_shipped_study_runs_at_its_tiny_scale(name, tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "disabled")
    study = load_study(name, "tiny")
    root = run_study(study, tmp_path / name, progress=False)
    section = (root / "section.md").read_text()
    assert section.startswith(f"## {study.title}") and (root / f"{name}.png").stat().st_size > 1000
    if study.analysis is None:
        rows = list(csv.DictReader((root / "table.csv").open()))
        assert [r["arm"] for r in rows] == [a.label for a in study.arms]
        for row in rows:
            assert all(math.isfinite(v) for v in json.loads(row["per_step"]))
            assert all(t <= 0.01 for t in json.loads(row["torn"]))  # bodies stay whole (docs/integrity.md)
    else:
        points = [json.loads(line) for p in root.rglob("points.jsonl") for line in p.read_text().splitlines()]
        assert points and all(math.isfinite(v) for p in points for k, v in p.items() if k in ("loss", "emd"))
