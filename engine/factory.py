"""Building an Engine from the environment: one place, used by the CLI and the queue worker alike."""

from __future__ import annotations

from engine.engine import Engine
from engine.settings import ModelSettings, SandboxSettings


def build_engine(with_model: bool = True) -> Engine:
    """The model is configured here but loaded on first use (`MODEL_*` settings, see engine.models).

    Raises SandboxUnavailable where untrusted code cannot be confined: no engine runs without its sandbox.
    """
    sandbox = SandboxSettings().build()
    if not with_model:
        return Engine(sandbox, None)

    def load() -> object:
        from engine.models import load_code_model

        return load_code_model(ModelSettings())

    return Engine(sandbox, load)  # type: ignore[arg-type]
