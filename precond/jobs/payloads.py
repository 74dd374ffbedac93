"""The payloads of the jobs the gateway makes for itself: never sent by a client, so they are not part of the
public API (`precond_client.schemas.api`, which ships in the client wheel) but of the wire contract between gateway and
worker."""

from __future__ import annotations

from pydantic import Field

from precond_client.schemas.api import (
    ADAPTER_ID_PATTERN,
    MAX_DEMONSTRATIONS,
    MAX_SOURCE_CHARS,
    PRECONDITIONS_DESCRIPTION,
    SPEC_DESCRIPTION,
    InferOptions,
    Preconditions,
    PreconditionSet,
    StrictBody,
)
from precond_client.schemas.training import TrainPolicyRequest


class ValidateRequest(StrictBody):
    """A worker job (kind `validate`, on the check queue): which demonstrated calls each rule would block.
    The gateway sends it for every new version of a precondition set that has demonstrations."""

    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS, description=SPEC_DESCRIPTION)
    preconditions: Preconditions = Field(default_factory=dict, description=PRECONDITIONS_DESCRIPTION)
    demonstrations: list[str] = Field(min_length=1, max_length=MAX_DEMONSTRATIONS)


class ReinferJob(StrictBody):
    """A worker job (kind `reinfer`): infer on the base version's spec with its stored demonstrations and the
    new ones, merge with its required and rejected rules, validate, and store the result as the next version
    (the gateway resolved the base; the worker appends only if it is still the latest)."""

    base: PreconditionSet
    demonstrations: list[str] = Field(min_length=1, max_length=MAX_DEMONSTRATIONS)
    actions: list[str] | None = None
    options: InferOptions = Field(default_factory=InferOptions)
    force: bool = False
    max_versions: int = Field(ge=1)
    max_bytes: int = Field(ge=1)
    max_tenant_bytes: int | None = Field(default=None, ge=1, description="Bytes of all the tenant's sets; None: "
                                         "unbounded (a job queued by a gateway that did not send it).")


class TrainPolicyJob(StrictBody):
    """A worker job (kind `train-policy`): train on `request` and store the adapter as version `version` of the
    tenant's adapter `adapter` (version 1: a new one), within the bounds the gateway sent (the worker's store
    enforces them atomically; the gateway only refuses early)."""

    request: TrainPolicyRequest
    adapter: str = Field(pattern=f"^{ADAPTER_ID_PATTERN}$")
    version: int = Field(ge=1)
    max_adapters: int = Field(ge=1)
    max_versions: int = Field(ge=1)
    max_tenant_bytes: int = Field(ge=1)
