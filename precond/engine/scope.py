"""Whose work is running: the scope the model backend keys its prompt-prefix caches by.

The queue worker runs each job inside `scoped(<the job's tenant tag>)`, so a tenant's request can reuse only
prefixes its own earlier requests computed (precond/engine/models/prefixes.py says why). A context variable rather than
a parameter: the scope is a property of the job, not of any one of the engine's many model calls.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

_SCOPE: ContextVar[str] = ContextVar("precond_cache_scope", default="")


@contextmanager
def scoped(name: str) -> Iterator[None]:
    token = _SCOPE.set(name)
    try:
        yield
    finally:
        _SCOPE.reset(token)


def current() -> str:
    return _SCOPE.get()
