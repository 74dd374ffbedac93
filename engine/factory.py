"""Building an Engine from the environment: one place, used by the CLI and the queue worker alike."""

from __future__ import annotations

from engine.engine import Engine
from engine.settings import ModelSettings, SandboxSettings
from sandbox import Sandbox


def build_engine(with_model: bool = True) -> Engine:
    """The model is configured here but loaded on first use (`MODEL_*` settings, see engine.models)."""
    settings = SandboxSettings()
    sandbox = Sandbox(settings.limits(), workers=settings.workers)
    if not with_model:
        return Engine(sandbox, None)

    def load() -> object:
        from engine.models import load_code_model

        return load_code_model(ModelSettings())

    return Engine(sandbox, load)  # type: ignore[arg-type]
