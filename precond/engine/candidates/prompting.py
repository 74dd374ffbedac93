"""Prompts as in the paper: code the model can continue, never natural-language instructions.

Inference: the observation function definitions, a demonstration, then the action's definition ending in
`assert`. Everything but the last part is the same for all actions of one prompt, which is what lets the
model backend compute that prefix once and reuse its key/value cache for every action.
Next action: the spec (optionally with the preconditions written in), few-shot demonstrations, then the
history; the model's next line is the predicted action.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from precond.engine.spec import Spec, action_header, asserted, observation_source, render_program


def inference_prefix(spec: Spec, actions: Sequence[str], demonstrations: Sequence[str]) -> str:
    demos = "\n".join(f"# Demonstration\n{demo.rstrip()}\n" for demo in demonstrations)
    return f"{observation_source(spec, actions)}\n{demos}\n# Preconditions of the actions, as assertions\n"


KNOWN_RULES_CHARS = 4000  # of the rules shown before the asked action: the prompt stays bounded


def inference_suffix(spec: Spec, action: str, known: Mapping[str, Sequence[str]] | None = None) -> str:
    """The action's definition ending in `assert`, after the rules `known` of its class's other actions.

    Shown what the evidence established for its siblings (`assert self.query_success` for a success notice),
    the model writes the rule of an action no demonstration shows (`not self.query_success` for the failure
    notice), where with the stub alone a small model writes `assert False`.
    """
    header = action_header(spec, action)
    cls = spec.methods[action].cls
    shown: list[str] = []
    used = 0
    for other, rules in (known or {}).items():
        if other == action or not rules or spec.methods[other].cls != cls:
            continue
        text = asserted(spec, other, rules)
        if used + len(text) > KNOWN_RULES_CHARS:
            continue
        shown.append(text)
        used += len(text)
    if not shown:
        return header
    opening, definition = header.split("\n", 1)
    return "\n".join((opening, *shown, definition))


def demo_windows(n_demos: int, prompts: int, per_prompt: int) -> list[list[int]]:
    """Which demonstrations each prompt shows: varied across prompts, as the paper does."""
    prompts = min(prompts, max(1, n_demos))
    return [[(p * per_prompt + k) % n_demos for k in range(min(per_prompt, n_demos))] for p in range(prompts)]


def next_action_prompt(
    spec: Spec,
    preconditions: dict[str, list[str]],
    demonstrations: Sequence[str],
    history: str,
    with_preconditions: bool,
) -> str:
    program = render_program(spec, preconditions) if with_preconditions else spec.source
    demos = "".join(f"# Demonstration\n{demo.rstrip()}\n\n" for demo in demonstrations)
    return f"{program.rstrip()}\n\n{demos}# Current\n{history.rstrip()}\n"
