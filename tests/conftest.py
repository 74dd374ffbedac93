from __future__ import annotations

import fcntl
import math
import os
import sys
from collections.abc import Callable, Iterator
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
GENERATED_FIXTURES = frozenset({"examples"})
"""A test that draws its cases with hypothesis and sizes their number with `examples` is marked `generated`: the
test command's fast step runs a tenth of its examples, its second step all of them."""


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--guard-cases", type=int, default=150,
                     help="generated rules and states the embedded guard is compared with Python on "
                          "(tests/client/test_guard_generated_rules.py)")
    parser.addoption("--examples-share", type=float, default=1.0,
                     help="the share of each generated test's hypothesis examples that is run (the `examples` "
                          "fixture; at least one): scripts/test.sh's fast step runs 0.1, its second step all")


def pytest_runtest_setup(item: pytest.Item) -> None:
    """...and is held to one thread here whatever the environment says."""
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Marks the stack and generated tests, and puts the files marked `long` first: pytest-xdist hands out files
    in this order when it is told not to reorder them (scripts/test.sh's fast step: `--no-loadscope-reorder`), so
    a long file starts early instead of ending the step alone on one core."""
    for item in items:
        fixtures = set(getattr(item, "fixturenames", ()))
        if STACK_FIXTURES & fixtures:
            item.add_marker(pytest.mark.stack)
        if GENERATED_FIXTURES & fixtures:
            item.add_marker(pytest.mark.generated)
    # stable: the other files keep their order behind the long ones
    items.sort(key=lambda item: item.get_closest_marker("long") is None)


@pytest.fixture()
def examples(pytestconfig: pytest.Config) -> Callable[[int], int]:
    """`examples(full)`: how many of a property test's `full` hypothesis examples run, `--examples-share` of them.
    A quick run draws fewer cases of the same property; the test command's second step draws them all."""
    share = float(pytestconfig.getoption("examples_share"))
    return lambda full: max(1, math.ceil(full * share))


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
