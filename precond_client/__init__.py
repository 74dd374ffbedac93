"""Python client of the precondition service: `Client` (blocking) and `AsyncClient` (asyncio), both over httpx.

Light on purpose: it needs httpx and pydantic and its own `precond_client.schemas` (the request and response
models, pydantic only), never torch, transformers or fastapi. Install it alone: docs/api.md, "Python client".

The names below are loaded when first used (PEP 562), so that the service, which shares
`precond_client.schemas` as its wire contract, imports those models without the client's transport.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_SOURCES: dict[str, tuple[str, ...]] = {
    "precond_client._core": ("Polling", "Progress", "Retry", "RetryHook"),
    "precond_client.aio": ("AsyncClient",),
    "precond_client.sync": ("Client",),
    "precond_client.errors": ("Cancelled", "Conflict", "InvalidInput", "JobTimeout", "NotFound", "PrecondError",
                              "RateLimited", "Unauthorized", "Unavailable"),
    "precond_client.history": ("History", "event"),
    "precond_client.schemas": (
        "AllowedCall", "CallVerdict", "CheckRequest", "CheckResponse", "HistoryEvent", "InferOptions",
        "InferRequest", "InferResponse", "JobProgress", "JobStatus", "NextActionOptions", "NextActionRequest",
        "NextActionResponse", "PreconditionSet", "PreconditionSetCreate", "PreconditionSetList",
        "PreconditionSetSummary", "PredictedAction", "PriorSource", "RuleChange", "RuleEdit", "RuleStatus", "SetDiff",
        "ToolCall",
    ),
    "precond_client.schemas.training": ("PolicyAdapter", "PolicyAdapterList", "TrainPolicyOptions",
                                        "TrainPolicyRequest"),
}
_WHERE = {name: module for module, names in _SOURCES.items() for name in names}
__all__ = [
    "AllowedCall",
    "AsyncClient",
    "CallVerdict",
    "Cancelled",
    "CheckRequest",
    "CheckResponse",
    "Client",
    "Conflict",
    "History",
    "HistoryEvent",
    "InferOptions",
    "InferRequest",
    "InferResponse",
    "InvalidInput",
    "JobProgress",
    "JobStatus",
    "JobTimeout",
    "NextActionOptions",
    "NextActionRequest",
    "NextActionResponse",
    "NotFound",
    "PolicyAdapter",
    "PolicyAdapterList",
    "Polling",
    "PrecondError",
    "PreconditionSet",
    "PreconditionSetCreate",
    "PreconditionSetList",
    "PreconditionSetSummary",
    "PredictedAction",
    "PriorSource",
    "Progress",
    "RateLimited",
    "Retry",
    "RetryHook",
    "RuleChange",
    "RuleEdit",
    "RuleStatus",
    "SetDiff",
    "ToolCall",
    "TrainPolicyOptions",
    "TrainPolicyRequest",
    "Unauthorized",
    "Unavailable",
    "event",
    "rules",
]


def __getattr__(name: str) -> Any:
    if name == "rules":
        return importlib.import_module("precond_client.rules")
    if name not in _WHERE:
        raise AttributeError(f"module 'precond_client' has no attribute {name!r}")
    value = getattr(importlib.import_module(_WHERE[name]), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__


if TYPE_CHECKING:
    from precond_client import rules
    from precond_client._core import Polling, Progress, Retry, RetryHook
    from precond_client.aio import AsyncClient
    from precond_client.errors import (
        Cancelled,
        Conflict,
        InvalidInput,
        JobTimeout,
        NotFound,
        PrecondError,
        RateLimited,
        Unauthorized,
        Unavailable,
    )
    from precond_client.history import History, event
    from precond_client.schemas import (
        AllowedCall,
        CallVerdict,
        CheckRequest,
        CheckResponse,
        HistoryEvent,
        InferOptions,
        InferRequest,
        InferResponse,
        JobProgress,
        JobStatus,
        NextActionOptions,
        NextActionRequest,
        NextActionResponse,
        PreconditionSet,
        PreconditionSetCreate,
        PreconditionSetList,
        PreconditionSetSummary,
        PredictedAction,
        PriorSource,
        RuleChange,
        RuleEdit,
        RuleStatus,
        SetDiff,
        ToolCall,
    )
    from precond_client.schemas.training import (
        PolicyAdapter,
        PolicyAdapterList,
        TrainPolicyOptions,
        TrainPolicyRequest,
    )
