"""schemathesis against openapi/openapi.json: no 5xx, every response as documented."""

from __future__ import annotations

from pathlib import Path

import pytest

from precond.stack import scenarios
from precond.stack.harness import FAST_SANDBOX, scenario_stack

pytestmark = pytest.mark.stack


def test_schemathesis_finds_no_5xx_and_no_schema_violation(tmp_path: Path, tiny_model_dir: Path) -> None:
    with scenario_stack("fuzz", tmp_path, tiny_model_dir, **FAST_SANDBOX) as stack:
        figures = scenarios.fuzz(stack, max_examples=15, seed=1, out=tmp_path / "schemathesis")
    assert figures["exit_code"] == 0, "\n".join(figures["summary"])
    assert figures["failures"] == [], figures
    assert figures["requests"] > 80, figures
    assert not [s for s in figures["by_status"] if s.startswith("5")], figures["by_status"]
    assert figures["gateway_alive"]
