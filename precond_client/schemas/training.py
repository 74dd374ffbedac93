"""The policy-training contract: behaviour cloning of the code model on a request's demonstrations (LoRA).

The paper's strongest base policy is BC: the code model fine-tuned on the demonstrations, then kept honest by
the preconditions (Algorithm 1 or the constrained mode). Everything here is bounded before any work is done:
the steps, the tokens of one example, the adapter's rank (hence its size).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from precond_client.schemas import (
    ADAPTER_ID_PATTERN,
    MAX_CALL_CHARS,
    MAX_DEMONSTRATIONS,
    MAX_SOURCE_CHARS,
    SPEC_DESCRIPTION,
    StrictBody,
)

MAX_TRAINING_STEPS = 400
MAX_EXAMPLE_TOKENS = 4_096
MAX_RANK = 32
MAX_ADAPTER_BYTES = 20 * 1024 * 1024
MAX_KNOWN_CALLS = 4_096


class TrainPolicyOptions(StrictBody):
    steps: int = Field(
        default=24, ge=1, le=MAX_TRAINING_STEPS,
        description="Optimizer steps, one demonstration each (seeded order, every demonstration before any "
        "repeats). 24 steps train an SGD domain's ten dialogs in 208-248 s on 2 CPU cores (docs/results.md).",
    )
    learning_rate: float = Field(default=1e-3, gt=0.0, le=1e-2)
    rank: int = Field(default=8, ge=1, le=MAX_RANK,
                      description="LoRA rank on the attention projections: the adapter's size grows with it.")
    max_tokens: int = Field(
        default=2_048, ge=64, le=MAX_EXAMPLE_TOKENS,
        description="Tokens of one example (the spec, then the demonstration); a longer one is cut at the end and "
        "the report says how many were.",
    )
    seed: int = Field(default=0, ge=0, le=2**31 - 1)


class TrainPolicyRequest(StrictBody):
    spec: str = Field(max_length=MAX_SOURCE_CHARS, description=SPEC_DESCRIPTION)
    demonstrations: list[str] = Field(
        min_length=1, max_length=MAX_DEMONSTRATIONS,
        description="Programs in the format of a next-action history; the loss is on their action lines (calls of "
        "the acting class's action functions: what the policy will be asked to write) and on the head of the line "
        "that ends each turn.",
    )
    options: TrainPolicyOptions = Field(default_factory=TrainPolicyOptions)


class TrainPolicyResult(StrictBody):
    """What a training produced and what it cost; stored beside the adapter as `policy.json`."""

    objective: str = Field(max_length=200,
                           description="What the loss was taken on (precond/engine/acting/training.py).")
    base_model: str
    base_sha256: str | None
    dtype: str
    steps: int
    examples: int
    action_lines: int
    truncated: int = Field(description="Examples cut at `options.max_tokens`.")
    losses: list[float] = Field(description="Mean loss over the action tokens, per step.")
    seconds: float
    trainable_parameters: int
    adapter_bytes: int
    options: TrainPolicyOptions
    calls: list[Annotated[str, Field(max_length=MAX_CALL_CHARS)]] = Field(
        default_factory=list, max_length=MAX_KNOWN_CALLS,
        description="The distinct action calls of the training demonstrations: the policy's vocabulary. The "
        "constrained mode draws argument values from them, as it does from a request's demonstrations, so a "
        "fine-tuned policy asked without any still knows its domain's slots.",
    )


class PolicyAdapter(StrictBody):
    """A tenant's stored trained policy, one version: what `POST /policies` made and `/next-action` names with
    `options.policy: "adapter:<reference>"`. Versions are never rewritten; a new training of the same adapter is
    its next version."""

    id: str = Field(pattern=f"^{ADAPTER_ID_PATTERN}$")
    version: int = Field(ge=1)
    reference: str = Field(description="`id@version`: what `options.policy` names as `adapter:<reference>`.")
    created: str = Field(description="When this version was stored (UTC, ISO 8601).")
    result: TrainPolicyResult


class PolicyAdapterList(StrictBody):
    adapters: list[PolicyAdapter] = Field(description="The latest version of each of the tenant's adapters.")
    bytes: int = Field(description="What all the tenant's stored versions take, against its bound.")
