from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from precond.stack.local import RedisServer
from precond.stack.tiny_model import build_tiny_model

# Two threads on two busy cores run torch ~10x slower than one.
torch.set_num_threads(1)

STACK_FIXTURES = frozenset({"stack", "own_stack", "unconfinable", "rate_limited", "small_answers", "redis_down",
                            "keyed", "guessed"})
"""Fixtures that start a stack (Redis, gateway and worker processes: precond.stack.local). A test that uses one,
directly or through another fixture, is marked `stack` and runs in the test command's second step; a test that
starts processes itself says so with `@pytest.mark.stack`."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--guard-cases", type=int, default=150,
                     help="generated rules and states the embedded guard is compared with Python on "
                          "(tests/client/test_guard_generated_rules.py)")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if STACK_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.stack)


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_tiny_model(tmp_path_factory.mktemp("tiny-model"))


@pytest.fixture()
def redis_server(tmp_path: Path) -> Iterator[RedisServer]:
    """A redis-server of the test's own (the project's tests never use a Redis they did not start)."""
    server = RedisServer(tmp_path)
    server.start()
    try:
        yield server
    finally:
        server.stop()
