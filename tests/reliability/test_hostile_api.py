"""The hostile corpus over HTTP: every request a 4xx with a clear message (or a verdict), nothing escapes."""

from __future__ import annotations

from pathlib import Path

import pytest

from precond.stack import scenarios
from precond.stack.harness import FAST_SANDBOX, scenario_stack

pytestmark = pytest.mark.stack


def test_hostile_requests_are_rejected_and_contained(tmp_path: Path, tiny_model_dir: Path) -> None:
    canaries = tmp_path / "canaries"
    canaries.mkdir()
    with scenario_stack("hostile", tmp_path, tiny_model_dir, **FAST_SANDBOX) as stack:
        figures = scenarios.hostile_input(stack, canaries)
    assert figures["problems"] == [], figures["problems"]
    assert figures["canaries_written"] == []
    assert figures["gateway_alive"] and figures["check_after"] == 200
    assert figures["worker_restarts"] == 0  # no hostile input took the worker down
    assert "500" not in figures["by_status"] and "-1" not in figures["by_status"], figures["by_status"]
    # Every request answered within its sandbox limits (2 s here) plus queueing behind the others.
    assert figures["slowest"]["max_ms"] < 30_000, figures["slowest"]
