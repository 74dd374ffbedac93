"""Model configuration, read from `MODEL_*` environment variables.

Everything a deployment changes without a code change lives here: which weights (the embedded 0.5B model on
a laptop, a mounted 7B model on a GPU host), where they run, and how many CPU threads they may take.
"""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

EMBEDDED = "embedded"


def default_cache_dir() -> Path:
    """Follow XDG so the converted weights survive reinstalls but stay out of the project tree."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "precond"


class ModelSettings(BaseSettings):
    """`path` is "embedded", a Hugging Face model directory, or a `.gguf` file.

    `device` and `dtype` default to "auto": CUDA in bfloat16 when present, else CPU in the dtype that
    generates fastest there. `threads` defaults to 1 because the worker usually shares its cores with the
    sandbox and other jobs; oversubscribed cores make torch an order of magnitude slower.
    """

    model_config = SettingsConfigDict(env_prefix="MODEL_", extra="ignore")

    path: str = EMBEDDED
    device: str = "auto"
    dtype: str = "auto"
    threads: int = Field(default=1, ge=1)
    cache_dir: Path = Field(default_factory=default_cache_dir)
    max_batch: int = Field(default=32, ge=1, description="Most sequences decoded in one forward pass.")
