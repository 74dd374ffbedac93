"""Building an Engine from the environment: one place, used by the CLI and the queue worker alike."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from engine.engine import Engine
from sandbox import Limits, Sandbox


class SandboxSettings(BaseSettings):
    """Limits on untrusted code, per sandbox call (`SANDBOX_*` environment variables)."""

    model_config = SettingsConfigDict(env_prefix="SANDBOX_")

    workers: int = Field(default=2, ge=1, le=64, description="Warm fork servers (parallel sandbox calls).")
    timeout_s: float = Field(default=10.0, gt=0, description="Wall-clock limit per call.")
    cpu_s: int = Field(default=10, ge=1, description="CPU seconds per call.")
    memory_mb: int = Field(default=1024, ge=64, description="Address-space limit per call.")
    open_files: int = Field(default=64, ge=8)
    output_bytes: int = Field(default=1_000_000, ge=1_000, description="Captured print output per call.")
    recursion: int = Field(default=400, ge=50)

    def limits(self) -> Limits:
        return Limits(
            timeout_s=self.timeout_s,
            cpu_s=self.cpu_s,
            memory_mb=self.memory_mb,
            open_files=self.open_files,
            output_bytes=self.output_bytes,
            recursion=self.recursion,
        )


def build_engine(with_model: bool = True) -> Engine:
    """The model is configured here but loaded on first use (`MODEL_*` settings, see engine.models)."""
    settings = SandboxSettings()
    sandbox = Sandbox(settings.limits(), workers=settings.workers)
    if not with_model:
        return Engine(sandbox, None)

    def load() -> object:
        from engine.models import ModelSettings, load_code_model

        return load_code_model(ModelSettings())

    return Engine(sandbox, load)  # type: ignore[arg-type]
