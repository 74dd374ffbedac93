"""What a room of the engine exports: its public names, each loaded from its module on first use.

A room's `__init__` names where each of its public names lives (`lazy`), so that `from precond.engine.judging import
select_rules` reads as the room's word, and importing a room loads none of its other modules (torch stays unloaded
until a model is built, as `precond_client/__init__.py` does for the client).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any


def lazy(package: str, sources: Mapping[str, Sequence[str]]) -> Callable[[str], Any]:
    """A module `__getattr__` for `package`: each name of `sources` (module -> names) from its module."""
    where = {name: module for module, names in sources.items() for name in names}

    def attribute(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    return attribute
