"""Building an Engine from the environment: one place, used by the CLI and the queue worker alike."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from precond.engine.engine import Engine
from precond.engine.settings import ModelSettings, SandboxSettings

if TYPE_CHECKING:
    from precond.engine.models import CodeModel
    from precond.engine.models.weights import Weights


def build_engine(with_model: bool = True, min_sandbox_workers: int = 1,
                 wrap_model: Callable[[CodeModel], CodeModel] | None = None, adapter: Path | None = None) -> Engine:
    """The model is configured here but loaded on first use (`MODEL_*` settings, see engine.models). The sandbox
    gets `SANDBOX_WORKERS` fork servers, or `min_sandbox_workers` (a queue worker's job slots) if more.
    `wrap_model` wraps the loaded model (the evaluation's memo of completions); `adapter` is a trained policy
    (`precond train-policy`) merged into the model's weights.

    Raises SandboxUnavailable where untrusted code cannot be confined: no engine runs without its sandbox.
    """
    settings = SandboxSettings()
    sandbox = settings.model_copy(update={"workers": max(settings.workers, min_sandbox_workers)}).build()
    if not with_model:
        return Engine(sandbox, None)

    def load() -> CodeModel:
        from precond.engine.models import load_code_model

        model = load_code_model(ModelSettings(), adapter)
        return model if wrap_model is None else wrap_model(model)

    return Engine(sandbox, load, training_weights)


def training_weights() -> Weights:
    """A fresh, trainable full-width copy of the configured model (`MODEL_*` settings): what a policy training
    loads, in the engine or in a worker's training process."""
    from precond.engine.models.weights import load_weights

    return load_weights(ModelSettings())
