"""Redis restarted under load with its append-only file (as docker-compose runs it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from precond.stack import scenarios
from precond.stack.harness import scenario_stack

pytestmark = pytest.mark.stack


@pytest.mark.parametrize("kill", [False, True], ids=["sigterm", "sigkill"])
def test_accepted_jobs_survive_a_redis_restart(tmp_path: Path, tiny_model_dir: Path, kill: bool) -> None:
    with scenario_stack("redis", tmp_path, tiny_model_dir, persistent=True) as stack:
        figures = scenarios.redis_restart(stack, jobs=12, millions=3, down_s=2.0, kill=kill, deadline_s=90)
    assert figures["lost"] == 0 and figures["succeeded"] == figures["accepted"] == 12, figures
    assert figures["queued_after_restart"] > 0, figures  # the test did restart Redis under queued jobs
    down = figures["answers_while_down"]
    for name, statuses in down.items():
        assert statuses == ([200] if name == "GET /health" else [503]), figures
    assert len(figures["503_with_retry_after"]) == len(down) - 1, figures
    assert figures["probe_latency_while_down"]["max_ms"] < 3000, figures  # 503 at once, no hanging
    # Back within the scenario's bound (a hang would fail here); how fast is bench/reliability.py's figure.
    assert figures["first_200_after_restart_s"] < 60 and figures["ready_after_restart_s"] < 60, figures
