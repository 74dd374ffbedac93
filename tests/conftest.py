from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from precond.stack.local import RedisServer
from precond.stack.tiny_model import build_tiny_model

# Two threads on two busy cores run torch ~10x slower than one.
torch.set_num_threads(1)


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
