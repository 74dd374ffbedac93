"""Replacements of libraries' private internals, each put in place only where what it replaces is there.

Three speed-ups replace methods of redis-py's asyncio connection (`patches.redis_packing`, `patches.redis_sending`,
`patches.redis_checkout`), and the gateway's HTTP protocol subclasses uvicorn's httptools protocol
(`precond/gateway/http_protocol.py`). Each names the attributes it replaces or reads; `apply` checks that they
exist before it patches, and when one is missing (a library version it was not written against) leaves the
library as it is and logs one line saying which patch is off and why: the service then runs at the library's own
speed, and behaves the same. pyproject.toml bounds those libraries to the versions the patches were checked
against; tests/jobs/test_patches.py switches each one off this way.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable

log = logging.getLogger("precond.patches")


def missing(module: str, owner: str, *names: str) -> list[str]:
    """Which of `owner`'s attributes `names` (or the owner itself, or its module) are not there."""
    try:
        found = getattr(importlib.import_module(module), owner)
    except (ImportError, AttributeError):
        return [f"{module}.{owner}"]
    return [f"{module}.{owner}.{name}" for name in names if not hasattr(found, name)]


def unassigned(module: str, owner: str, method: str, *names: str) -> list[str]:
    """Which of the instance attributes `names` `owner.method` never assigns (read from its code): attributes an
    object gets in `__init__` or on connecting are not on its class for `missing` to see."""
    try:
        code = getattr(getattr(importlib.import_module(module), owner), method).__code__
    except (ImportError, AttributeError):
        return [f"{module}.{owner}.{method}"]
    return [f"{module}.{owner}().{name}" for name in names if name not in code.co_names]


def apply(name: str, absent: list[str], patch: Callable[[], None], instead: str = "the library's own code") -> bool:
    """Run `patch` unless something it replaces is `absent`; whether it ran."""
    if absent:
        log.warning("%s: off, this library version lacks %s; %s runs instead", name, ", ".join(absent), instead)
        return False
    patch()
    return True
