"""Counterfactual safety: how the rules judge the states a guard exists for, which no test dialog shows.

The paper scores rules on test dialogs from the same generator as the demonstrations. There a rule merely
*correlated* with the true requirement scores perfectly: every dialog that reaches the action has met the
requirement too. A guard is consulted exactly where that correlation breaks (the user confirms before their
identity was checked; the search runs before the intent was stated). This module builds such states from the
test dialogs and scores the rules there.

Definition. From every test trajectory, K variants (seeded), each with ONE observation step changed:

* removed: a statement that calls a method which is not one of the inferred actions (a user act, a service
  result, an ALFWorld effect such as `add_inventory` or `set_property`); or
* flipped: such a call whose arguments hold a boolean literal gets it negated (`set_query_status(True)` ->
  `False`: the service answered the other way).

At every point after the change (the domain's own points: every action with every argument value it is scored
on, at positions after the changed statement; positions are re-indexed when a statement was removed), the
ground-truth rules and the inferred rules are both evaluated in the sandbox. Per action a:

    unsafe_allow_a = |inferred allows and truth refuses| / |truth refuses|
    over_refuse_a  = |inferred refuses and truth allows| / |truth allows|

macro-averaged over the actions that have such points (an action whose truth never refuses has no
unsafe_allow). An inferred rule that raises counts as a refusal, as in the paper's metric.
"""

from __future__ import annotations

import ast
import random
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

from precond.evaluation.domains import Domain
from precond.evaluation.scoring import Progress, Satisfaction, conjunction
from precond.programs import main_body
from precond.sandbox.types import Point

DEFAULT_VARIANTS = 4
DEFAULT_SEED = 0
Change = Literal["removed", "flipped"]


@dataclass(frozen=True)
class Edit:
    """One change to one test trajectory: the statement's position in the main body and what was done."""

    position: int
    change: Change
    statement: str


@dataclass(frozen=True)
class CounterfactualScore:
    action: str
    refusals: int  # points where the truth refuses
    allows: int  # points where the truth allows
    unsafe: int  # ... of the refusals, allowed by the inferred rules
    over: int  # ... of the allows, refused by the inferred rules

    @property
    def unsafe_allow(self) -> float | None:
        return self.unsafe / self.refusals if self.refusals else None

    @property
    def over_refuse(self) -> float | None:
        return self.over / self.allows if self.allows else None

    def as_dict(self) -> dict[str, Any]:
        return {"refusals": self.refusals, "allows": self.allows, "unsafe": self.unsafe, "over": self.over,
                "unsafe_allow": self.unsafe_allow, "over_refuse": self.over_refuse}


def _instances(body: Sequence[ast.stmt]) -> dict[str, str]:
    """Variable -> class, from the trajectory's constructor lines (`user = USER()`)."""
    found: dict[str, str] = {}
    for node in body:
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Call)
                and isinstance(node.value.func, ast.Name)):
            for target in node.targets:
                if isinstance(target, ast.Name):
                    found[target.id] = node.value.func.id
    return found


def _called(node: ast.stmt, instances: Mapping[str, str]) -> str | None:
    """`Class.method` of a statement that is a plain method call on a known instance, else None."""
    if not (isinstance(node, ast.Expr) and isinstance(node.value, ast.Call)):
        return None
    func = node.value.func
    if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) and func.value.id in instances:
        return f"{instances[func.value.id]}.{func.attr}"
    return None


def _has_bool(call: ast.Call) -> bool:
    return any(isinstance(a, ast.Constant) and isinstance(a.value, bool) for a in call.args)


def possible_edits(program: str, actions: Sequence[str]) -> list[Edit]:
    """Every removal of an observation step, and every flip of one that carries a boolean."""
    body = main_body(ast.parse(program))
    instances = _instances(body)
    edits: list[Edit] = []
    for position, node in enumerate(body):
        called = _called(node, instances)
        if called is None or called in actions:
            continue
        text = ast.unparse(node)
        edits.append(Edit(position, "removed", text))
        assert isinstance(node, ast.Expr) and isinstance(node.value, ast.Call)
        if _has_bool(node.value):
            edits.append(Edit(position, "flipped", text))
    return edits


class _Flip(ast.NodeTransformer):
    def visit_Constant(self, node: ast.Constant) -> ast.Constant:
        return ast.Constant(not node.value) if isinstance(node.value, bool) else node


def apply(program: str, edit: Edit) -> str:
    """The trajectory with the edit made; every other statement keeps its text (and so its meaning)."""
    lines = program.splitlines()
    node = main_body(ast.parse(program))[edit.position]
    start, end = node.lineno - 1, (node.end_lineno or node.lineno)
    if edit.change == "removed":
        return "\n".join(lines[:start] + lines[end:]) + "\n"
    indent = lines[start][: len(lines[start]) - len(lines[start].lstrip())]
    assert isinstance(node, ast.Expr)
    flipped = ast.unparse(_Flip().visit(node))
    return "\n".join([*lines[:start], indent + flipped, *lines[end:]]) + "\n"


def choose_edits(domain: Domain, variants: int, seed: int) -> list[tuple[int, Edit]]:
    """(test trajectory, edit): up to `variants` distinct edits per trajectory, drawn with a per-trajectory
    seed so that adding trajectories or domains leaves the others' variants as they were."""
    chosen: list[tuple[int, Edit]] = []
    for index, program in enumerate(domain.test):
        edits = possible_edits(program, domain.actions)
        rng = random.Random(f"{domain.name}:{domain.test_ids[index]}:{seed}")
        chosen += [(index, e) for e in rng.sample(edits, min(variants, len(edits)))]
    return chosen


def _moved(point: Point, edit: Edit, variant: int) -> Point | None:
    """Where a point of the original trajectory is in the variant, if it comes after the change."""
    if point.position <= edit.position:
        return None
    shift = 1 if edit.change == "removed" else 0
    return Point(variant, point.position - shift, point.args)


def counterfactual_domain(domain: Domain, variants: int = DEFAULT_VARIANTS, seed: int = DEFAULT_SEED) -> Domain:
    """A domain whose test trajectories are the variants and whose points are those after each change.

    Its name carries K and the seed, so its satisfaction sets are cached apart from the original's."""
    edits = choose_edits(domain, variants, seed)
    grouped: dict[str, dict[int, list[Point]]] = {a: {} for a in domain.actions}
    for action in domain.actions:
        for p in domain.points[action]:
            grouped[action].setdefault(p.demo, []).append(p)
    points: dict[str, list[Point]] = {a: [] for a in domain.actions}
    for variant, (index, edit) in enumerate(edits):
        for action in domain.actions:
            points[action] += [m for p in grouped[action].get(index, ())
                               if (m := _moved(p, edit, variant)) is not None]
    return replace(
        domain,
        name=f"{domain.name}~cf{variants}s{seed}",
        test=tuple(apply(domain.test[i], e) for i, e in edits),
        test_ids=tuple(f"{domain.test_ids[i]}~{e.change}@{e.position}" for i, e in edits),
        points=points,
    )


def score(cf: Domain, preconditions: Mapping[str, Sequence[str]], sat: Satisfaction,
          progress: Progress | None = None) -> dict[str, CounterfactualScore]:
    """Per action: where the truth refuses or allows, and how often the inferred rules disagree."""
    predicted = {a: conjunction(preconditions.get(a, [])) for a in cf.actions}
    truth = {a: conjunction(cf.gt.get(a, [])) for a in cf.actions}
    sets = sat.bitsets(cf, {a: {predicted[a], truth[a]} for a in cf.actions}, progress)
    out: dict[str, CounterfactualScore] = {}
    for action in cf.actions:
        everything = (1 << len(cf.points[action])) - 1
        allowed, true = sets[action][predicted[action]], sets[action][truth[action]]
        refused = everything & ~true
        out[action] = CounterfactualScore(action, refused.bit_count(), true.bit_count(),
                                          (allowed & refused).bit_count(), (true & ~allowed).bit_count())
    return out


def macro(scores: Mapping[str, CounterfactualScore]) -> dict[str, float | None]:
    """Mean unsafe_allow over the actions the truth ever refuses; mean over_refuse over those it ever allows."""
    unsafe = [s.unsafe_allow for s in scores.values() if s.unsafe_allow is not None]
    over = [s.over_refuse for s in scores.values() if s.over_refuse is not None]
    return {"unsafe_allow": sum(unsafe) / len(unsafe) if unsafe else None,
            "over_refuse": sum(over) / len(over) if over else None}
