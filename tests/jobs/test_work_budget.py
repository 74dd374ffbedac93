"""One work budget: the gateway's estimate before queueing and the sandbox's exact count read one variable."""

from __future__ import annotations

import pytest

from precond.engine.settings import SandboxSettings
from precond.gateway.settings import GatewaySettings


@pytest.mark.parametrize("variable", ["PRECOND_MAX_WORK_POINTS", "SANDBOX_MAX_POINTS"])
def test_one_variable_sets_the_estimate_and_the_count(monkeypatch: pytest.MonkeyPatch, variable: str) -> None:
    monkeypatch.delenv("PRECOND_MAX_WORK_POINTS", raising=False)
    monkeypatch.delenv("SANDBOX_MAX_POINTS", raising=False)
    monkeypatch.setenv(variable, "1234")
    assert GatewaySettings().max_work_points == 1234
    assert SandboxSettings().limits().max_points == 1234
