"""The constrained next action: enumerate the calls the preconditions allow now, let the model choose among them.

Algorithm 1 resamples a small model that keeps proposing the same forbidden call; here the sandbox judges every
call the agent could make (its actions × argument values seen in the spec's defaults, the history and the
demonstrations) in one batch, and the model only ranks the allowed ones by log-likelihood after the next-action
prompt (`CodeModel.score`, one token tree over the shared prefix): the allowed actions first and then that
action's arguments one at a time (`choose_by: action`, the default), or every allowed line in one pass
(`choose_by: line`, up to MAX_LINES of them). A chosen call
is allowed by construction; an empty allowed set is an answer of its own ("nothing allowed"), never a
forbidden call.

Whether the agent acts again in the same turn is the model's call too: after the first action, the turn ends
when the next line is likelier to be no action (another actor's, `user`, or an observation of the agent's
own, `system.set_query_status` after a service call) than an action (`ends_turn`).
"""

from __future__ import annotations

import ast
import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from precond.engine.spec import Spec

MAX_ENUMERATED = 2048
"""Calls judged per step; beyond it the product of argument values is cut (the reason says so)."""
MAX_PER_ACTION = 512
"""Calls of one action: a two-argument action over every object seen must not crowd out the others."""
MAX_LINES = 64
"""Up to this many allowed calls, every full line is scored in one pass (exact: the likeliest allowed line)."""
MAX_SCORED = 48
"""Beyond MAX_LINES: values of one argument scored in one pass; the rest are left unscored (never chosen)."""
MAX_VALUES = 64
UNNAMED = "*"

Scalar = str | int | float | bool | None


@dataclass(frozen=True)
class Candidates:
    calls: list[str]
    action: dict[str, str]
    """call → qualified action (`SYSTEM.REQUEST`)."""
    head: dict[str, str]
    """call → its line head (`system.REQUEST(`)."""
    args: dict[str, tuple[Scalar, ...]]
    truncated: bool


def _literal(node: ast.expr) -> tuple[bool, Scalar]:
    try:
        value = ast.literal_eval(node)
    except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError):
        return False, None
    return (True, value) if value is None or isinstance(value, str | int | float | bool) else (False, None)


def argument_values(spec: Spec, programs: Iterable[ast.Module]) -> tuple[dict[str, list[Scalar]], list[Scalar]]:
    """Literal arguments per parameter name (from calls of spec methods, and defaults), and every literal seen.

    Parameter names carry the domain (`slot`, `recep`): a value passed as `slot` anywhere is a candidate for
    every `slot` parameter. Values passed where no parameter names them (`*args`, as in
    `agent.update_visible_objects('cabinet 1', 'apple 2')`: what the agent has seen) are candidates for
    every parameter. The flat list is the fallback for a parameter no call names.
    """
    by_name: dict[str, list[Scalar]] = {}
    every: list[Scalar] = []
    methods = {m.name: m for m in spec.methods.values()}

    def note(name: str, value: Scalar) -> None:
        if value not in by_name.setdefault(name, []):
            by_name[name].append(value)
        if value not in every:
            every.append(value)

    for method in spec.methods.values():
        args = method.node.args
        for param, default in zip(args.args[len(args.args) - len(args.defaults):], args.defaults, strict=True):
            ok, value = _literal(default)
            if ok:
                note(param.arg, value)
    for tree in programs:
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)):
                continue
            called = methods.get(node.func.attr)
            names: Sequence[str] = called.positional if called else ()
            for k, arg in enumerate(node.args):
                ok, value = _literal(arg)
                if ok:
                    note(names[k] if k < len(names) else UNNAMED, value)
    unnamed = by_name.pop(UNNAMED, [])
    return {name: values + [v for v in unnamed if v not in values] for name, values in by_name.items()}, every


def enumerate_calls(
    spec: Spec, actions: Iterable[str], receivers: Mapping[str, str], values: Mapping[str, list[Scalar]],
    fallback: Sequence[Scalar],
) -> Candidates:
    """Every call `var.method(args)` of the actions whose class has an instance in the history, in spec order."""
    variable = {cls: var for var, cls in reversed(list(receivers.items()))}  # the first instance of each class
    calls: list[str] = []
    action_of: dict[str, str] = {}
    head_of: dict[str, str] = {}
    args_of: dict[str, tuple[Scalar, ...]] = {}
    truncated = False
    for action in actions:
        method = spec.methods.get(action)
        var = variable.get(method.cls) if method else None
        if method is None or var is None:
            continue
        domains = [list(values.get(p) or fallback)[:MAX_VALUES] for p in method.positional]
        head = f"{var}.{method.name}("
        for k, args in enumerate(itertools.product(*domains)):
            if len(calls) >= MAX_ENUMERATED or k >= MAX_PER_ACTION:
                truncated = True
                break
            call = f"{head}{', '.join(repr(a) for a in args)})"
            calls.append(call)
            action_of[call], head_of[call], args_of[call] = action, head, tuple(args)
    return Candidates(calls, action_of, head_of, args_of, truncated)


def argument_texts(head: str, chosen: Sequence[Scalar], options: Sequence[Scalar], last: bool) -> list[str]:
    """The line so far with each option as the next argument: the full line for the last argument, else
    `agent.take('apple 1` (without the closing quote, which the tokenizer merges with what follows: a text
    cut inside a token would be scored as if the model had to write that rare token)."""
    before = "".join(f"{a!r}, " for a in chosen)
    if last:
        return [f"{head}{before}{v!r})\n" for v in options]
    return [f"{head}{before}{repr(v)[:-1] if isinstance(v, str) else repr(v)}" for v in options]


@dataclass(frozen=True)
class TurnHeads:
    """Line heads whose likelihoods decide whether the agent acts again: its receiver (`system`), its own
    methods that are no action (observations the environment reports, `system.set_query_status`), and the
    other actors (`user`)."""

    own: list[str]
    observations: list[str]
    others: list[str]

    @property
    def all(self) -> list[str]:
        return [*self.own, *self.observations, *self.others]


def turn_heads(spec: Spec, receivers: Mapping[str, str], actions: Iterable[str]) -> TurnHeads:
    """Heads end where the tokenizer ends a token (`system`, `system.set_query_status`): `system.` or
    `...status(` would be scored as if the model had to write a lone `.` or `(`, which it never does."""
    wanted = set(actions)
    acting = {spec.methods[a].cls for a in wanted if a in spec.methods}
    own = [var for var, cls in receivers.items() if cls in acting]
    observations = [f"{var}.{m.name}" for var in own for m in spec.methods.values()
                    if m.cls == receivers[var] and m.qualname not in wanted and not m.name.startswith("_")]
    return TurnHeads(own, observations, [var for var, cls in receivers.items() if cls not in acting])


def extensions(heads: Iterable[str], every: Iterable[str]) -> dict[str, list[str]]:
    """Per head, the other actions' heads that continue its text (`system.OFFER` -> `system.OFFER_INTENT`),
    only the nearest of a chain: the likelihood of a head is the mass of every line that starts with it."""
    known = set(every)
    out: dict[str, list[str]] = {}
    for head in heads:
        longer = [o for o in known if o != head and o.startswith(head)]
        out[head] = sorted(o for o in longer if not any(o != p and o.startswith(p) for p in longer))
    return out


def own_mass(head: str, scores: Mapping[str, float], longer: Mapping[str, Sequence[str]]) -> float:
    """A head's log-likelihood without the mass of the longer heads that continue it: scored as text,
    `system.OFFER` also counts every `system.OFFER_INTENT(...)` line, which would make the shorter action
    win whenever both are allowed."""
    rest = math.exp(scores[head]) - sum(math.exp(scores[o]) for o in longer.get(head, ()))
    return math.log(rest) if rest > 0 else -math.inf


def ends_turn(heads: TurnHeads, scores: Mapping[str, float]) -> bool:
    """Whether the next line is likelier no action than an action: P(other actor) + P(observation) against
    P(agent) - P(observation). Compared at a line's first words, as greedy decoding decides; comparing `user`
    with a whole `system.REQUEST('city')` line would favour ending the turn for being the shorter text."""
    if not heads.own or not (heads.others or heads.observations):
        return False
    observed = sum(math.exp(scores[h]) for h in heads.observations)
    stop = sum(math.exp(scores[h]) for h in heads.others) + observed
    return stop > sum(math.exp(scores[h]) for h in heads.own) - observed


def indentation(history: str) -> str:
    """The indentation the next line of the history takes (top level, or inside the episode's function)."""
    lines = [line for line in history.splitlines() if line.strip()]
    return lines[-1][: len(lines[-1]) - len(lines[-1].lstrip())] if lines else ""
