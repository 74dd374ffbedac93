from __future__ import annotations

import fcntl
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from precond.stack.local import RedisServer

# Two threads on two busy cores run torch ~10x slower than one. torch is imported by the tests that use it, not
# here: collecting (in every pytest-xdist process) stays cheap. It reads this when it is imported...
os.environ.setdefault("OMP_NUM_THREADS", "1")

STACK_FIXTURES = frozenset({"stack", "own_stack", "unconfinable", "rate_limited", "small_answers", "redis_down",
                            "keyed", "guessed"})
"""Fixtures that start a stack (Redis, gateway and worker processes: precond.stack.local). A test that uses one,
directly or through another fixture, is marked `stack` and runs in the test command's second step; a test that
starts processes itself says so with `@pytest.mark.stack`."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--guard-cases", type=int, default=150,
                     help="generated rules and states the embedded guard is compared with Python on "
                          "(tests/client/test_guard_generated_rules.py)")


def pytest_runtest_setup(item: pytest.Item) -> None:
    """...and is held to one thread here whatever the environment says."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if STACK_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.stack)


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Built once a run: the processes of one pytest-xdist run share the first one's copy (no test writes into
    it), so the others import neither torch nor transformers to build their own."""
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    directory = shared / "tiny-model"
    with (shared / "tiny-model.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (shared / "tiny-model.done").exists():
            from precond.stack.tiny_model import build_tiny_model

            build_tiny_model(directory)
            (shared / "tiny-model.done").touch()
    return directory


@pytest.fixture()
def redis_server(tmp_path: Path) -> Iterator[RedisServer]:
    """A redis-server of the test's own (the project's tests never use a Redis they did not start)."""
    server = RedisServer(tmp_path)
    server.start()
    try:
        yield server
    finally:
        server.stop()
