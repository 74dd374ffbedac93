"""Python client of the precondition service: `Client` (blocking) and `AsyncClient` (asyncio), both over httpx.

Light on purpose: it needs httpx and pydantic and this project's `schemas` (the request and response models,
pydantic only), never torch, transformers or fastapi. Install it alone: README.md, "Python client".
"""

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
from precond_client.sync import Client
from schemas.api import (
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
    RuleChange,
    RuleEdit,
    SetDiff,
    ToolCall,
)

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
    "Polling",
    "PrecondError",
    "PreconditionSet",
    "PreconditionSetCreate",
    "PreconditionSetList",
    "PreconditionSetSummary",
    "PredictedAction",
    "Progress",
    "RateLimited",
    "Retry",
    "RetryHook",
    "RuleChange",
    "RuleEdit",
    "SetDiff",
    "ToolCall",
    "Unauthorized",
    "Unavailable",
    "event",
    "rules",
]
