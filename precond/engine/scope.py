"""Whose work is running: the scope the model backend keys its prompt-prefix caches by, and the sandbox what it
remembers of a request's text and its warm children.

The queue worker runs each job inside `scoped(<the job's tenant tag>)`, so a tenant's request can reuse only
prefixes its own earlier requests computed (precond/engine/models/prefixes.py says why), and only the sandbox
state its own earlier checks left. A job whose result is shared with other tenants runs with `warm=False`: a warm
sandbox child answers with what its tenant ran there before, and a shared result must depend on the request
alone. Context variables rather than parameters: the scope is a property of the job, not of any one of the
engine's many model and sandbox calls.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

_SCOPE: ContextVar[str] = ContextVar("precond_cache_scope", default="")
_WARM: ContextVar[bool] = ContextVar("precond_warm_children", default=True)


@contextmanager
def scoped(name: str, warm: bool = True) -> Iterator[None]:
    token, warm_token = _SCOPE.set(name), _WARM.set(warm)
    try:
        yield
    finally:
        _SCOPE.reset(token)
        _WARM.reset(warm_token)


def current() -> str:
    return _SCOPE.get()


def warm() -> bool:
    """Whether a warm sandbox child of the scope may answer (False: every check runs on a fresh child)."""
    return _WARM.get()
