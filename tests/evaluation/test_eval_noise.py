"""The noise and sparsity harness: seeded, realistic errors in the demonstrations only."""

from __future__ import annotations

import json
from typing import Any

import pytest

from precond.evaluation.configs import GRIDS, parse_config
from precond.evaluation.noise import corrupt, sample
from precond.evaluation.sweep import Setting, collect, setting
from tests.engine.conftest import SHARED


@pytest.fixture(scope="module")
def demos() -> list[str]:
    data: dict[str, Any] = json.loads((SHARED / "sgd" / "Restaurants_1.json").read_text())
    return [d["program"] for d in data["demos"]]


def _system_steps(programs: list[str]) -> int:
    return sum(1 for p in programs for line in p.splitlines()
               if line.startswith("system.") and not line.startswith("system.set_query_status"))


def test_errors_touch_the_share_of_system_steps_asked_and_nothing_else(demos: list[str]) -> None:
    assert corrupt(demos, 0.0, 0) == demos
    noisy = corrupt(demos, 0.1, 0)
    assert noisy == corrupt(demos, 0.1, 0) and noisy != corrupt(demos, 0.1, 1)  # seeded
    changed = sum(a != b for a, b in zip(demos, noisy, strict=True))
    assert changed >= 1
    for clean, dirty in zip(demos, noisy, strict=True):
        # user steps and the API's answers are never touched: only the agent slips
        keep = ("user.", "system.set_query_status")
        assert [x for x in clean.splitlines() if x.startswith(keep)] == [
            x for x in dirty.splitlines() if x.startswith(keep)]
    assert abs(_system_steps(noisy) - _system_steps(demos)) <= round(0.1 * _system_steps(demos))


def test_a_re_asked_slot_was_informed_before(demos: list[str]) -> None:
    for seed in range(5):
        for program in corrupt(demos, 0.1, seed):
            lines = program.splitlines()
            for k, line in enumerate(lines):
                if line.startswith("system.REQUEST("):
                    slot = line[len("system.REQUEST("):-1]
                    informed = f"user.INFORM({slot})" in lines[:k]
                    original = any(line in d.splitlines() for d in demos)
                    assert original or informed


def test_samples_are_seeded_subsets_in_order(demos: list[str]) -> None:
    chosen = sample(demos, 3, 1)
    assert chosen == sample(demos, 3, 1) and len(chosen) == 3
    assert [demos.index(d) for d in chosen] == sorted(demos.index(d) for d in chosen)
    assert sample(demos, 10, 0) == demos


def test_the_sweep_grid_pairs_strict_and_tolerant_settings() -> None:
    names = GRIDS["noise"]
    config = parse_config("enumerate/recency/tol=0/noise=0.05/sample=2")
    assert config.name in names and config.noise == 0.05 and config.sample == 2
    assert config.infer_options().tolerance == 0
    assert setting("enumerate/recency/tol=0/noise=0.05/sample=2") == Setting(10, 0.05, 0.0)
    assert setting("enumerate/recency") is None
    rows = [{"config": n, "domain": d, "benchmark": "sgd", "macro": {"f1": f}}
            for n, d, f in [("enumerate/recency/tol=0/noise=0.05/sample=0", "A", 0.8),
                            ("enumerate/recency/tol=0/noise=0.05/sample=1", "A", 0.6),
                            ("enumerate/recency/tol=0/noise=0.05/sample=0", "B", 1.0),
                            ("enumerate/recency/tol=0/noise=0.05/sample=1", "B", 0.8)]]
    cells = collect(rows)[Setting(10, 0.05, 0.0)]
    assert cells["A"].mean == pytest.approx(0.7) and cells["A"].sd == pytest.approx(0.1)
    assert cells["mean"].mean == pytest.approx(0.8) and cells["mean"].seeds == 2
