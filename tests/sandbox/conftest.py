"""Sandboxes shared by the sandbox tests: one with small limits for hostile code, one for real data."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sandbox_helpers import SMALL

from precond.sandbox import Limits, Sandbox


@pytest.fixture(scope="session")
def small() -> Iterator[Sandbox]:
    with Sandbox(SMALL, workers=2) as sandbox:
        yield sandbox


@pytest.fixture(scope="session")
def big() -> Iterator[Sandbox]:
    with Sandbox(Limits(timeout_s=120, cpu_s=120, memory_mb=4096), workers=2) as sandbox:
        yield sandbox
