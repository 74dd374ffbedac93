"""The code model as a judge where the demonstrations cannot decide, choosing among executed candidates.

Two questions are left open by the evidence. An action never demonstrated (`zero-shot`): every candidate holds
vacuously. A condition that held at every occurrence but was already true before the user's last turn
(`phase`): it may be a requirement (`NOTIFY_SUCCESS` needs `query_success`) or just where the episode happened
to be. The paper lets the model write rules and hopes free samples agree; here the model *scores* the
candidates the sandbox already validated, in a prompt that shows the rules the evidence did establish for the
other actions (so the model answers by analogy with grounded rules, not from a blank page):

    <observation functions>  # Demonstration ...  class SYSTEM:  def INFORM(self, slot): assert <kept rule> ...
        def NOTIFY_FAILURE(self):
            assert <candidate>

A candidate wins only when the model is confident on both counts measured: its log-likelihood leads the next
candidate's by `MARGIN` nats, and it is more likely under this action's name than under a neutral one
(`def check(self):`, pointwise mutual information above zero), so a condition the model would write for any
method (copying the rule just above) does not count as judgment about this action. Otherwise the evidence's
answer stands (no rule for a zero-shot action, the phase stays dropped).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal, Protocol

from precond.engine.spec import Spec, observation_source

MARGIN = 2.0
MAX_OPTIONS = 16
"""Candidates scored per question (the undecided first, then the shortest): each is a batch row, and what
the model prefers is a short condition on the state (the longer ones are near-synonyms of those)."""

Kind = Literal["zero-shot", "phase"]


class Scorer(Protocol):
    def score(self, prefix: str, continuations: Sequence[str]) -> list[float]: ...


@dataclass(frozen=True)
class Question:
    action: str
    kind: Kind
    options: tuple[str, ...]
    """Representatives of the valid, informative clusters the model chooses among."""
    open: frozenset[str]
    """The options the evidence left undecided: only one of these can be adopted."""


@dataclass(frozen=True)
class Verdict:
    question: Question
    scores: Mapping[str, float]
    neutral: Mapping[str, float]
    adopted: str | None

    def describe(self, expression: str) -> str:
        """The model's judgment of one option in words, for the candidate report."""
        top = max(self.scores, key=lambda e: self.scores[e])
        ll, pmi = self.scores[expression], self.scores[expression] - self.neutral.get(expression, 0.0)
        what = ("never demonstrated, so the evidence cannot choose" if self.question.kind == "zero-shot"
                else "the evidence cannot tell a phase from a requirement")
        if expression == self.adopted:
            return (f"kept by the code model's judgment ({what}): log-likelihood {ll:.2f}, the best by "
                    f"{self.margin:.1f} nats, and {pmi:+.2f} more likely for this action than for a neutral one")
        if expression == top:
            return (f"the code model preferred it ({what}) but not confidently: lead {self.margin:.1f} nats "
                    f"(needs {MARGIN}), {pmi:+.2f} nats over a neutral action; not kept")
        return f"the code model preferred {top!r} ({what}); log-likelihood here {ll:.2f}"

    @property
    def margin(self) -> float:
        ranked = sorted(self.scores.values(), reverse=True)
        return ranked[0] - ranked[1] if len(ranked) > 1 else float("inf")


def prompt(spec: Spec, actions: Sequence[str], demonstration: str, rules: Mapping[str, Sequence[str]],
           action: str, name: str | None = None) -> str:
    """The inference prompt with the established rules of the class written out, ending in `action`'s assert.

    `name` replaces the action's name in its header (the neutral prompt of the PMI).
    """
    method = spec.methods[action]
    indent = " " * (method.node.col_offset or 4)
    lines = [f"class {method.cls}:"]
    for other in actions:
        theirs = spec.methods[other]
        if other == action or theirs.cls != method.cls or not rules.get(other):
            continue
        lines.append(f"{indent}def {theirs.name}({', '.join(('self', *theirs.signature))}):")
        lines += [f"{indent * 2}assert {rule}" for rule in rules[other]]
    lines.append(f"{indent}def {name or method.name}({', '.join(('self', *method.signature))}):")
    lines.append(f"{indent * 2}assert")
    demo = f"# Demonstration\n{demonstration.rstrip()}\n" if demonstration else ""
    return (f"{observation_source(spec, actions)}\n{demo}\n# Preconditions of the actions, as assertions\n"
            + "\n".join(lines))


def decide(model: Scorer, spec: Spec, actions: Sequence[str], demonstration: str,
           rules: Mapping[str, Sequence[str]], question: Question) -> Verdict:
    """Score every option after the action's `assert`, and the leader after a neutral header."""
    options = list(question.options)
    texts = [f" {option}\n" for option in options]
    scores = dict(zip(options, model.score(prompt(spec, actions, demonstration, rules, question.action), texts),
                      strict=True))
    top = max(options, key=lambda e: scores[e])
    neutral_prompt = prompt(spec, actions, demonstration, rules, question.action, name="check")
    (neutral,) = model.score(neutral_prompt, [f" {top}\n"])
    verdict = Verdict(question, scores, {top: neutral}, None)
    confident = verdict.margin >= MARGIN and scores[top] - neutral > 0
    return Verdict(question, scores, {top: neutral}, top if confident and top in question.open else None)


def question(action: str, kind: Kind, undecided: Sequence[str], others: Sequence[str]) -> Question:
    """The undecided options first, then the others shortest first, at most MAX_OPTIONS rows in all."""
    first = list(dict.fromkeys(undecided))[:MAX_OPTIONS]
    rest = sorted((e for e in dict.fromkeys(others) if e not in first), key=len)
    return Question(action, kind, tuple(first + rest[: MAX_OPTIONS - len(first)]), frozenset(first))
