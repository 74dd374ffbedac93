"""Building an Engine from the environment: one place, used by the CLI and the queue worker alike."""

from __future__ import annotations

from engine.engine import Engine
from engine.settings import ModelSettings, SandboxSettings


def build_engine(with_model: bool = True, min_sandbox_workers: int = 1) -> Engine:
    """The model is configured here but loaded on first use (`MODEL_*` settings, see engine.models). The sandbox
    gets `SANDBOX_WORKERS` fork servers, or `min_sandbox_workers` (a queue worker's job slots) if more.

    Raises SandboxUnavailable where untrusted code cannot be confined: no engine runs without its sandbox.
    """
    settings = SandboxSettings()
    sandbox = settings.model_copy(update={"workers": max(settings.workers, min_sandbox_workers)}).build()
    if not with_model:
        return Engine(sandbox, None)

    def load() -> object:
        from engine.models import load_code_model

        return load_code_model(ModelSettings())

    return Engine(sandbox, load)  # type: ignore[arg-type]
