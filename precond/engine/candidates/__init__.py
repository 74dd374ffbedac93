"""Generating candidate rules: prompts the code model continues, its samples parsed, the model-free
enumeration, a tool-calling agent's conditions and relations, the shipped rule library.

Its public names are importable from here, each loaded from its module on first use (`engine.faces`)."""

from __future__ import annotations

from precond.engine.faces import lazy

_SOURCES: dict[str, tuple[str, ...]] = {
    "precond.engine.candidates.enumeration": ("StateModel", "enumerate_atoms"),
    "precond.engine.candidates.library": (
        "LIBRARY_FILE", "Library", "LibrarySource", "PREFIX", "SIGNED", "SIGNED_SOURCE", "shipped", "to_json",
    ),
    "precond.engine.candidates.parsing": ("parse_samples",),
    "precond.engine.candidates.prompting": ("inference_prefix", "inference_suffix"),
    "precond.engine.candidates.tool_conditions": (
        "ALLOWANCES", "ARGUMENT_KEY", "MAX_CELLS", "MAX_KEYS", "allowance", "allowance_form", "arithmetic", "key",
        "separating", "tool_atoms",
    ),
    "precond.engine.candidates.tool_facts": ("tool_class",),
    "precond.engine.candidates.tool_relations": ("labels_only", "relations"),
}
__all__ = sorted(name for names in _SOURCES.values() for name in names)
__getattr__ = lazy(__name__, _SOURCES)
