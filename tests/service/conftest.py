"""One real stack (Redis, gateway, one worker with the real engine and the tiny model) per test module."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from stack.local import Stack, make_stack, serving


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory, tiny_model_dir: Path) -> Iterator[Stack]:
    """Modules that break things (Redis, workers) build their own stacks and do not disturb this one."""
    stack = make_stack(
        tmp_path_factory.mktemp("stack"), tiny_model_dir, PRECOND_QUEUE_MAX_JOBS="3", PRECOND_JOB_TIMEOUT_S="120"
    )
    with serving(stack, workers=1):
        yield stack


@pytest.fixture()
def client(stack: Stack) -> Iterator[httpx.Client]:
    with stack.http() as http:
        yield http
