"""Bodies of the three operations (infer, next-action, check) and of jobs and errors.

They live here, not in `service/` or `worker/`, because the CLI, the gateway, the queue payloads and the
engine all speak them: a field renamed in one place must fail everywhere at once.
Size bounds are part of the contract: they turn hostile inputs into 422s before any work is queued.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

MAX_SOURCE_CHARS = 200_000
MAX_DEMONSTRATIONS = 200
MAX_ASSERTIONS_PER_ACTION = 32
MAX_ASSERTION_CHARS = 1_000
MAX_CALLS = 64
MAX_CALL_CHARS = 1_000

Generator = Literal["model", "enumerate"]
Ranking = Literal["subsumption", "recency", "marginal"]

SourceText = Field(max_length=MAX_SOURCE_CHARS)


class _Body(BaseModel):
    """Unknown fields are errors: a typo in an option must not silently fall back to a default."""

    model_config = ConfigDict(extra="forbid")


MAX_ACTIONS = 256
MAX_ACTION_CHARS = 200
Assertion = Annotated[str, StringConstraints(max_length=MAX_ASSERTION_CHARS)]
Preconditions = Annotated[
    dict[
        Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)],
        Annotated[list[Assertion], Field(max_length=MAX_ASSERTIONS_PER_ACTION)],
    ],
    Field(max_length=MAX_ACTIONS),
]
"""Action (`Class.method`) → assertions; every bound is enforced here, before any work is queued."""


class InferOptions(_Body):
    generators: list[Generator] = Field(
        default=["model", "enumerate"],
        min_length=1,
        max_length=2,
        description="Candidate generators. The default scores best on the dev numbers (docs/results.md); "
        "['enumerate'] alone is the model-free fast path (about a second, F1 within 0.002 on SGD).",
    )
    ranking: Ranking = Field(
        default="recency",
        description="'subsumption' is the paper's eq. (hopt); 'recency' (default, best on the dev numbers) keeps "
        "argument conditions and conditions made true since the agent's previous turn; 'marginal' keeps "
        "conditions while they still exclude enough points.",
    )
    samples_per_prompt: int = Field(default=4, ge=1, le=64)
    prompts_per_action: int = Field(
        default=2, ge=1, le=MAX_DEMONSTRATIONS, description="How many demonstrations to vary across prompts."
    )
    demonstrations_per_prompt: int = Field(default=1, ge=1, le=10)
    temperature: float = Field(default=0.8, ge=0.0, le=2.0)
    top_p: float = Field(default=0.95, gt=0.0, le=1.0)
    max_new_tokens: int = Field(default=48, ge=4, le=256)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)


class InferRequest(_Body):
    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS)
    demonstrations: list[str] = Field(min_length=1, max_length=MAX_DEMONSTRATIONS)
    actions: list[str] | None = Field(default=None, max_length=256)
    options: InferOptions = Field(default_factory=InferOptions)


class CandidateReport(_Body):
    assertion: str
    source: Generator
    valid: bool
    cluster: int | None = None
    support: int = Field(description="|C_h|: demonstration points (position x arguments) where it holds.")
    kept: bool
    reason: str | None = Field(default=None, description="Why a candidate was rejected or found invalid.")


class StageCounts(_Body):
    sampled: int = 0
    parsed: int = 0
    valid: int = 0
    clusters: int = 0
    kept: int = 0


class InferStats(_Body):
    actions: dict[str, StageCounts]
    total: StageCounts
    seconds: dict[str, float] = Field(description="Wall time per phase: trace, generate, validate, rank.")


class ModelInfo(_Body):
    name: str
    sha256: str | None = None
    device: str
    dtype: str


class InferResponse(_Body):
    preconditions: dict[str, list[str]]
    program: str
    candidates: dict[str, list[CandidateReport]]
    stats: InferStats
    model: ModelInfo | None = Field(default=None, description="None when no generator used a model.")


class NextActionOptions(_Body):
    max_attempts: int = Field(default=5, ge=1, le=50)
    max_actions: int = Field(default=1, ge=1, le=20)
    preconditions_in_prompt: bool = False
    verify: bool = Field(default=True, description="Algorithm 1's verified sampling; false: greedy only.")
    temperature: float = Field(default=0.8, ge=0.0, le=2.0)
    max_new_tokens: int = Field(default=32, ge=4, le=128)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)


class NextActionRequest(_Body):
    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS)
    preconditions: Preconditions = Field(default_factory=dict)
    demonstrations: list[str] = Field(default_factory=list, max_length=MAX_DEMONSTRATIONS)
    history: str = Field(max_length=MAX_SOURCE_CHARS)
    options: NextActionOptions = Field(default_factory=NextActionOptions)


class Rejection(_Body):
    call: str
    violations: list[str] = Field(default_factory=list)
    reason: str | None = None


class PredictedAction(_Body):
    call: str
    verified: bool
    attempts: int
    rejected: list[Rejection] = Field(default_factory=list)


class NextActionResponse(_Body):
    actions: list[PredictedAction]
    model: ModelInfo | None = None


class CheckRequest(_Body):
    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS)
    preconditions: Preconditions = Field(default_factory=dict)
    history: str = Field(max_length=MAX_SOURCE_CHARS)
    calls: list[str] = Field(min_length=1, max_length=MAX_CALLS)


class CallVerdict(_Body):
    call: str
    allowed: bool
    violations: list[str] = Field(default_factory=list)
    error: str | None = Field(default=None, description="Exception raised by the call other than an assertion.")


class CheckResponse(_Body):
    results: list[CallVerdict]


JobKind = Literal["infer", "next-action", "check"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class ErrorInfo(_Body):
    type: str
    message: str
    field: str | None = None


class ErrorResponse(_Body):
    error: ErrorInfo
    request_id: str


class JobProgress(_Body):
    phase: str = "queued"
    done: int = 0
    total: int = 0


class JobStatus(_Body):
    id: str
    kind: JobKind
    status: JobState
    progress: JobProgress = Field(default_factory=JobProgress)
    result: dict[str, Any] | None = None
    error: ErrorInfo | None = None
