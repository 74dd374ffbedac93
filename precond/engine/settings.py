"""The engine's two deployable parts, configured from the environment: the model (`MODEL_*`) and the
sandbox (`SANDBOX_*`).

Everything a deployment changes without a code change lives here: which weights (the embedded 0.5B model on
a laptop, a mounted 7B model on a GPU host), where they run, how many CPU threads they may take, and the
limits on untrusted code. The `MODEL_*` variables are also part of every job id: the gateway reads them
from the environment itself (`jobs.queue.keys.model_identity`), so that it never loads this module, the engine
or the sandbox.
"""

from __future__ import annotations

import os
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

from pydantic import AliasChoices, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from precond.sandbox import Sandbox
from precond.sandbox.types import Limits

EMBEDDED = "embedded"
QUANT_CHOICES = ("auto", "none", "int8")
PREFIX_CACHE_MB = 32
"""The default bound on kept prompt prefixes: with the embedded model in its default settings a worker that fills
it stays under 1 GB resident (docs/model-speed.md, bench/prefix_memory_bench.py)."""
RETIRED_PREFIX_VARIABLE = "MODEL_PREFIX_CACHE_TOKENS"


def default_cache_dir() -> Path:
    """Follow XDG so the converted weights survive reinstalls but stay out of the project tree."""
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg else Path.home() / ".cache"
    return base / "precond"


class ModelSettings(BaseSettings):
    """`path` is "embedded", a Hugging Face model directory, or a `.gguf` file.

    `device` and `dtype` default to "auto": CUDA in bfloat16 when present, else CPU in bfloat16 only where the
    CPU has native bf16 dot products (avx512_bf16 or amx_bf16), float32 elsewhere (bf16 is 3-10x slower
    there; see bench/model_bench.py). The choice and its reason are in every response's `model` block.
    `threads` defaults to 1 because the worker usually shares its cores with the sandbox and other jobs;
    oversubscribed cores make torch an order of magnitude slower.
    """

    model_config = SettingsConfigDict(env_prefix="MODEL_", extra="ignore")

    path: str = Field(
        default=EMBEDDED,
        description="`embedded` (Qwen2.5-Coder-0.5B-Instruct from the `model` extra), a Hugging Face model "
        "directory, or a `.gguf` file.",
    )
    device: str = Field(default="auto", description="`auto` (CUDA when present, else CPU), `cpu`, `cuda`, ...")
    dtype: str = Field(
        default="auto",
        description="`auto` (bfloat16 on CUDA; on CPU bfloat16 with avx512_bf16/amx_bf16, else float32) or a "
        "torch dtype name (`float32`, `bfloat16`, `float16`).",
    )
    quant: str = Field(
        default="auto",
        description="`auto` (int8 weights on a CPU with int8 dot products: avx512_vnni, avx_vnni or amx_int8; else "
        "none), `none` (weights in `dtype`) or `int8` (refused at load where the CPU or torch cannot run it). "
        "docs/model-speed.md has the speed and accuracy of each.",
    )
    threads: int = Field(default=1, ge=1, description="CPU threads torch may use.")
    cache_dir: Path = Field(
        default_factory=default_cache_dir,
        description="Where converted weights (full-width and int8, keyed by the source's sha256) are kept. Unset: "
        "`$XDG_CACHE_HOME/precond` (`~/.cache/precond`).",
    )
    max_batch: int = Field(default=32, ge=1, description="Most sequences decoded in one forward pass.")
    prefix_cache_mb: int = Field(
        default=PREFIX_CACHE_MB, ge=0,
        description="MiB of key/value caches of prompt prefixes kept for reuse, over all tenants (each tenant reuses "
        "only its own, and evicts only its own, least recently used first; one prompt larger than the bound is kept "
        "alone where no other tenant holds any). A token of the "
        "embedded 0.5B model holds 12 KB in bfloat16, 24 KB in float32, so the default keeps 1-2 next-action "
        "prompts in bfloat16 and about one in float32. docs/model-speed.md has what a serving worker holds.",
    )
    prefix_cache_tenant_mb: int | None = Field(
        default=None, ge=0,
        description="MiB of kept prompt prefixes one tenant may hold (unset: MODEL_PREFIX_CACHE_MB). A tenant's "
        "prompt evicts only that tenant's own entries; where the others leave no room it is not kept. With more "
        "tenants than MODEL_PREFIX_CACHE_MB / this, a busy tenant can find the store full: size the two together.",
    )
    prefix_cache_idle_s: float = Field(
        default=600.0, gt=0,
        description="Seconds a kept prompt prefix stays unused before it goes, so the memory of a tenant that "
        "stopped comes back by time, never by another tenant's request.",
    )

    @model_validator(mode="before")
    @classmethod
    def _no_token_bound(cls, data: Any) -> Any:
        """The bound was once set in tokens; a deployment still setting that would otherwise run with the
        default bound unawares (unknown variables are ignored)."""
        given = isinstance(data, dict) and any(key.lower() == "prefix_cache_tokens" for key in data)
        if given or any(name.upper() == RETIRED_PREFIX_VARIABLE for name in os.environ):
            raise ValueError(f"{RETIRED_PREFIX_VARIABLE} is no longer read: the bound on kept prompt prefixes is "
                             "set in MiB by MODEL_PREFIX_CACHE_MB (a token costs 12 KB of the embedded model's "
                             "keys and values in bfloat16, 24 KB in float32)")
        return data

    @field_validator("quant")
    @classmethod
    def _known_quant(cls, value: str) -> str:
        """Named here so a typo fails when the settings are read, before any weights are."""
        if value not in QUANT_CHOICES:
            raise ValueError(f"MODEL_QUANT={value!r} is not one of {', '.join(QUANT_CHOICES)}")
        return value


_LIMITS = Limits()
SCORING_TIMEOUT_S = 120.0
SCORING_MEMORY_MB = 4096


class SandboxSettings(BaseSettings):
    """Limits on untrusted code, per sandbox call; one field per `sandbox.Limits` field, same defaults."""

    model_config = SettingsConfigDict(env_prefix="SANDBOX_", extra="ignore")

    workers: int = Field(default=2, ge=1, le=64, description="Warm fork servers (parallel sandbox calls).")
    timeout_s: float = Field(default=_LIMITS.timeout_s, gt=0, description="Wall-clock limit per call.")
    cpu_s: int = Field(default=_LIMITS.cpu_s, ge=1, description="CPU seconds per call.")
    memory_mb: int = Field(default=_LIMITS.memory_mb, ge=64, description="Address-space limit per call.")
    open_files: int = Field(default=_LIMITS.open_files, ge=8, description="Open file descriptors per call.")
    output_bytes: int = Field(
        default=_LIMITS.output_bytes, ge=1_000, description="Captured print output per call."
    )
    result_bytes: int = Field(
        default=_LIMITS.result_bytes, ge=1_000, description="Largest answer a sandbox call may send back."
    )
    recursion: int = Field(default=_LIMITS.recursion, ge=50, description="Python recursion limit per call.")
    unit_cpu_s: float = Field(
        default=_LIMITS.unit_cpu_s, gt=0,
        description="CPU seconds for one part of a call (a candidate, a proposed call); over it, that part "
        "fails alone.",
    )
    max_failed_units: int = Field(
        default=_LIMITS.max_failed_units, ge=0,
        description="Parts of one call that may fail on a limit before the call does.",
    )
    max_points: int = Field(
        default=_LIMITS.max_points, ge=1,
        validation_alias=AliasChoices("PRECOND_MAX_WORK_POINTS", "SANDBOX_MAX_POINTS"),
        description="Most points (demonstration positions x argument tuples) of one action a call may judge: "
        "the gateway's work budget (`PRECOND_MAX_WORK_POINTS`, estimated from the request's text before it "
        "is queued), counted exactly here.",
    )
    allow_unconfined: bool = Field(
        default=False,
        description="DEVELOPMENT ONLY: run untrusted code without the seccomp policy when it cannot be installed "
        "(logged as an error, shown by /health and /ready). Off: such a worker refuses all work.",
    )

    def limits(self) -> Limits:
        return Limits(**{f.name: getattr(self, f.name) for f in fields(Limits)})

    def build(self) -> Sandbox:
        """Raises SandboxUnavailable when the kernel policy cannot be set up (unless allowed)."""
        return Sandbox(self.limits(), workers=self.workers, allow_unconfined=self.allow_unconfined)

    def build_for_scoring(self) -> Sandbox:
        """The evaluation's sandbox: the same confinement and limits, but the time and memory of a whole
        domain's test trajectories in one call (at least `SCORING_TIMEOUT_S` and `SCORING_MEMORY_MB`)."""
        limits = replace(self.limits(), timeout_s=max(self.timeout_s, SCORING_TIMEOUT_S),
                         cpu_s=max(self.cpu_s, int(SCORING_TIMEOUT_S)),
                         memory_mb=max(self.memory_mb, SCORING_MEMORY_MB))
        return Sandbox(limits, workers=self.workers, allow_unconfined=self.allow_unconfined)
