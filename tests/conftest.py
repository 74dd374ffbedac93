from __future__ import annotations

from pathlib import Path

import pytest
import torch

from stack.tiny_model import build_tiny_model

# Two threads on two busy cores run torch ~10x slower than one.
torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_tiny_model(tmp_path_factory.mktemp("tiny-model"))
