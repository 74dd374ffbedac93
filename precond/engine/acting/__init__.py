"""Acting on the rules: the next action (Algorithm 1's sampling with verification, or constrained) and
behaviour cloning of the code model on the demonstrations.

Its public names are importable from here, each loaded from its module on first use (`engine.faces`)."""

from __future__ import annotations

from precond.engine.faces import lazy

_SOURCES: dict[str, tuple[str, ...]] = {
    "precond.engine.acting.next_action": ("NextActionPlanner",),
    "precond.engine.acting.training": ("OBJECTIVE", "train_policy"),
}
__all__ = sorted(name for names in _SOURCES.values() for name in names)
__getattr__ = lazy(__name__, _SOURCES)
