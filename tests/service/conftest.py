"""One real stack (Redis, gateway, one worker with the real engine and the tiny model) per test module."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from precond.stack.local import Stack, make_stack, serving


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


@pytest.fixture()
def acme(stack: Stack, keys: tuple[Path, dict[str, str]]) -> Iterator[httpx.Client]:
    """A client with the key of tenant `acme`, in a module whose `keys` fixture made one (path, tenant → key)."""
    from tests.service.test_tenants import client_for

    with client_for(stack, keys[1]["acme"]) as client:
        yield client


@pytest.fixture()
def globex(stack: Stack, keys: tuple[Path, dict[str, str]]) -> Iterator[httpx.Client]:
    from tests.service.test_tenants import client_for

    with client_for(stack, keys[1]["globex"]) as client:
        yield client
