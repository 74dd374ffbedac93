"""Labelled calls in an infer request: the calls the rules must refuse, and those they must allow.

Demonstrations alone say where an action *was* called, never where it must not be; a successful run can even
break the policy itself, and strict validation then refutes the right rule. A labelled call fixes both: a call
labelled 'refuse' (an incident, a review, a label) is evidence against every rule that allows it, including a
demonstrated call (which then stops counting for a rule); a call labelled 'allow' is one more call the rules
must allow.

For an action with labelled calls the rules are chosen by what separates the two sides: a small disjunction
of conjunctions (`separate`) of the conditions already judged (the enumerator's, the model's), false at every
call to refuse and true at as many calls to allow as it can be, each term with as few conditions as the
evidence needs (one, else two). Beside it the ranking's other rules stay where they allow every call to allow,
an assumed one (a possible correlate) too: more labels never leave a guard weaker than the demonstrations alone
made it, and a refusal by an assumed rule says it is assumed. Last, for a tool spec, an allowance the policy states
tightens the rule (`allowance_tables`: one k for every call, or a k by category, only where one k cannot
separate the calls the rest leaves allowed). Nothing here runs untrusted code: the sandbox judged every
condition at every labelled call (`Labelled.points` are its points).
"""

from __future__ import annotations

import ast
import re
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from precond.engine.candidates.tool_conditions import ARGUMENT_KEY, allowance, arithmetic
from precond.engine.judging import categorical, run_tasks
from precond.engine.judging.allowance_tables import Table, best_allowance, held_terms
from precond.engine.judging.allowance_tables import table as table_of
from precond.engine.judging.evidence import OccurrenceIndex, gather
from precond.engine.judging.ranking import Candidate, Cluster
from precond.engine.judging.report import Ranked
from precond.engine.spec import Spec
from precond.sandbox.types import CandidateResult, Point, TraceResult
from precond_client.schemas import Counterexamples, Decided
from precond_client.schemas.errors import InvalidInput

MAX_TERMS = 4
"""Disjuncts of a separating rule: policies say "if A, or B, or C"."""
MAX_PAIRED = 80
"""Conditions paired into two-condition terms (the most calls to allow first): 3,160 pairs at most."""
REFUSE, ALLOW = "refuse", "allow"


@dataclass(frozen=True)
class Case:
    """One labelled call: the action, the verdict it must get, where it is (a run and a 1-based line)."""

    action: str
    verdict: str
    name: str
    run: int
    """Index into `Labelled.programs` (runs given as programs), or -1 for a demonstration."""
    demonstration: int | None
    line: int


@dataclass
class Labelled:
    programs: list[str]
    """The runs given as programs (not demonstrations), in the sandbox's order."""
    cases: list[Case]

    def actions(self) -> set[str]:
        return {c.action for c in self.cases}

    def demonstrated(self, verdict: str) -> dict[tuple[int, int], Case]:
        return {(c.demonstration, c.line): c for c in self.cases
                if c.demonstration is not None and c.verdict == verdict}


def read(spec: Spec, runs: Sequence[Counterexamples], demos: Sequence[str], actions: Sequence[str]) -> Labelled:
    """The request's labelled calls, each checked: a line that is a call of one of the asked actions, and no
    history and call labelled both ways (422 naming the field, or both fields)."""
    labelled = Labelled([], [])
    seen: dict[str, tuple[str, str]] = {}
    for i, run in enumerate(runs):
        if run.demonstration is not None and run.demonstration >= len(demos):
            raise InvalidInput(f"there are {len(demos)} demonstrations", field=f"counterexamples[{i}].demonstration")
        text = demos[run.demonstration] if run.demonstration is not None else str(run.program)
        if run.demonstration is None:
            labelled.programs.append(text)
        lines = text.splitlines()
        for j, call in enumerate(run.calls):
            where = f"counterexamples[{i}].calls[{j}]"
            action = _action_on(spec, lines, call.line, f"{where}.line", actions)
            key = "\n".join(lines[: call.line])
            other = seen.setdefault(key, (call.verdict, where))
            if other[0] != call.verdict:
                raise InvalidInput(f"labels the same history and call as {other[1]} the other way",
                                   field=where)
            labelled.cases.append(Case(action, call.verdict, call.name or where,
                                       -1 if run.demonstration is not None else len(labelled.programs) - 1,
                                       run.demonstration, call.line))
    return labelled


def of_actions(spec: Spec, runs: Sequence[Counterexamples], demos: Sequence[str],
               actions: Sequence[str]) -> list[Counterexamples]:
    """The runs whose every labelled call is a call of one of `actions`: a re-inference of some actions learns
    from the labels of those actions, and the stored labels of the others wait for theirs."""
    kept = []
    for run in runs:
        text = demos[run.demonstration] if run.demonstration is not None and run.demonstration < len(demos) \
            else str(run.program)
        try:
            for call in run.calls:
                _action_on(spec, text.splitlines(), call.line, "", actions)
        except InvalidInput:
            continue
        kept.append(run)
    return kept


def _action_on(spec: Spec, lines: Sequence[str], line: int, where: str, actions: Sequence[str]) -> str:
    if line > len(lines):
        raise InvalidInput(f"the run has {len(lines)} lines", field=where)
    try:
        node = ast.parse(lines[line - 1].strip(), mode="eval").body
    except SyntaxError:
        node = None
    name = node.func.attr if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) else None
    action = next((q for q in actions if name is not None and spec.methods[q].name == name), None)
    if action is None:
        raise InvalidInput(f"line {line} is not a call of an action rules are inferred for "
                           f"({', '.join(actions)[:200]})", field=where)
    return action


def points(labelled: Labelled, trace: TraceResult) -> dict[str, list[tuple[Case, Point]]]:
    """Each labelled call of a run given as a program, at its point in that run's trace."""
    found: dict[str, list[tuple[Case, Point]]] = {}
    for case in labelled.cases:
        if case.demonstration is not None:
            continue
        occurrence = _at_line(trace, case.action, case.run, case.line)
        if occurrence is not None:
            found.setdefault(case.action, []).append((case, occurrence))
    return found


def demonstrated_points(labelled: Labelled, trace: TraceResult, action: str) -> dict[Point, Case]:
    """The demonstrated calls of `action` that a label names, by their point in the demonstrations' trace."""
    found = {}
    for case in labelled.cases:
        if case.demonstration is not None and case.action == action:
            occurrence = _at_line(trace, action, case.demonstration, case.line)
            if occurrence is not None:
                found[occurrence] = case
    return found


def _at_line(trace: TraceResult, action: str, run: int, line: int) -> Point | None:
    info = trace.actions.get(action)
    for occurrence in info.occurrences if info else ():
        if occurrence.demo == run and trace.positions[run][occurrence.position].line == line:
            return occurrence
    return None


def task_of(labelled: Labelled, demos: Sequence[str]) -> Callable[[Point | Case], str]:
    """The task of a demonstrated call (its point) or a labelled call: that of its run (`run_tasks`)."""
    named = run_tasks.tasks([*demos, *labelled.programs])

    def of(where: Point | Case) -> str:
        if isinstance(where, Point):
            return named[where.demo]
        if where.demonstration is not None:
            return named[where.demonstration]
        return named[len(demos) + where.run]
    return of


@dataclass(frozen=True)
class Example:
    case: Case | None
    """None: a demonstrated call no label names (to allow)."""
    refuse: bool


@dataclass(frozen=True)
class Separation:
    ranked: Ranked
    refuses: dict[str, list[str]]
    """Per kept rule, the names of the calls labelled 'refuse' it refuses."""
    refuses_allowed: dict[str, list[str]]
    """Per kept rule, the calls labelled 'allow' (or demonstrated) it refuses: where it is wrong."""
    exempt: set[Point]
    """Demonstrated calls labelled 'refuse': verification skips them (the kept rules refuse them by design)."""
    unrefused: list[str]
    """The calls labelled 'refuse' that no kept rule refuses: nothing the conditions say separates them."""
    unshown: bool
    """No demonstrated call to allow: none demonstrated, or each labelled 'refuse'. The action is then refused
    (`options.unseen`) unless its labelled calls give it a rule, as a never-demonstrated one is."""
    conflicts: list[str] = field(default_factory=list)
    """Per rule made from the labels that refuses calls demonstrated or labelled 'allow', in words: which of those,
    and which calls labelled 'refuse' it refuses. Such a rule is `assumed` (a human decides), never established."""
    outcome: Outcome | None = None
    """Where the judged conditions hold among the examples, and which the labels chose."""
    made: Made | None = None
    """The ranking being changed, to adopt more rules (`shared_rules`)."""


def separate(action: str, ranked: Ranked, demo_points: Sequence[Point], occurrences: Sequence[Point],
             labelled_demos: Mapping[Point, Case], case_points: Sequence[tuple[Case, Point]],
             case_results: Mapping[str, CandidateResult], case_order: Sequence[Point],
             policy: set[str] | None = None, tasks: Callable[[Point | Case], str] | None = None) -> Separation:
    """The action's rules chosen against its labelled calls (module docstring). `policy`: the conditions
    the separating rules are made of when given (a tool spec's conditions over results and arguments); `tasks`:
    the task a demonstrated call (its point) or a labelled call of another run belongs to (`run_tasks.own_task`)."""
    examples, demo_bits = _examples(occurrences, labelled_demos, demo_points, case_points)
    case_bits = [_index(case_order, point) for _, point in case_points]
    positive = sum(1 << k for k, e in enumerate(examples) if not e.refuse)
    negative = sum(1 << k for k, e in enumerate(examples) if e.refuse)
    truth = _truth(ranked, demo_bits, case_bits, case_results, bool(case_points))
    unshown = all(e.refuse for e in examples[:len(examples) - len(case_points)])
    kept, notes = _kept(ranked, truth, positive, negative, unshown)
    remaining = negative & ~_refused_by(kept - categorical.refinements(ranked.reasons), truth, negative)
    pool = {e: t for e, t in truth.items() if e in policy and allowance(e) < 0 and not ARGUMENT_KEY.match(e)
            } if policy else truth
    # with no call to allow (none demonstrated or labelled 'allow'), nothing bounds a separating rule
    # from above: only the limits a tool's policy states are learned from the calls to refuse (`_limits`)
    task_of = [tasks(case or occurrence) for case, occurrence in _sources(examples, occurrences, case_points)] \
        if tasks else None
    required, learned = _smallest(pool, positive, remaining, task_of, negative) if positive else (
        _limits(pool, negative, remaining) if policy else [], [])
    every = (1 << len(examples)) - 1
    table = _tightened(truth, policy, positive, negative, remaining, required, learned, every) \
        if policy and (kept or required or learned) else None
    required += table if isinstance(table, list) else []
    chosen = [c for c in ranked.chosen if c.representative.expression in kept]
    by_text = {r.expression: r for r in ranked.results}
    for e in required:
        chosen.append(Cluster((Candidate(e, "enumerate", by_text[e].satisfied),)))
        notes[e] = ("kept: holds at every call to allow and refuses calls labelled 'refuse'" if positive else
                    "kept: a limit that refuses calls labelled 'refuse'; no call of the action is labelled 'allow' "
                    "or demonstrated") + run_tasks.across(negative & ~truth.get(e, 0), negative, task_of)
    at_demos = {r.expression: r.satisfied for r in ranked.results}
    added: list[tuple[str, int, int, str]] = []
    """Rules made here: the text, where it holds at the demonstrations and at the examples, the reason."""
    if learned:
        added.append((_text(learned), held_terms(learned, at_demos, (1 << len(demo_points)) - 1),
                      held_terms(learned, truth, every),
                      f"kept: separates the calls labelled 'refuse' from the calls to allow "
                      f"({len(learned)} term{'s' if len(learned) > 1 else ''})"))
    if isinstance(table, Table):
        added.append((table.text, table.held(at_demos, (1 << len(demo_points)) - 1), table.held(truth, every),
                      table.reason))
    made = Made(ranked, OccurrenceIndex.of(demo_points, occurrences), chosen, {**ranked.reasons, **notes},
                {**{e: d for e, d in ranked.decided.items() if e in kept}, **dict.fromkeys(required, "established")})
    for expression, satisfied, held, reason in added:
        made.adopt(expression, satisfied, reason)
        truth[expression] = held
    from_labels = [e for e in [*required, *(c for t in learned for c in t)] if negative & ~truth.get(e, 0)]
    outcome = Outcome([_name(e) for e in examples], truth, positive, negative, from_labels)
    return made.separation(outcome, [e for e, *_ in added], {p for p, c in labelled_demos.items()
                                                             if c.verdict == REFUSE}, unshown)


def _examples(occurrences: Sequence[Point], labelled_demos: Mapping[Point, Case], demo_points: Sequence[Point],
              case_points: Sequence[tuple[Case, Point]]) -> tuple[list[Example], list[int | None]]:
    """The demonstrated calls (their labels, where named) then the labelled calls of other runs, and per
    demonstrated call its bit among the demonstrations' points."""
    examples: list[Example] = []
    demo_bits: list[int | None] = []
    for occurrence in dict.fromkeys(occurrences):
        case = labelled_demos.get(occurrence)
        examples.append(Example(case, case is not None and case.verdict == REFUSE))
        demo_bits.append(_index(demo_points, occurrence))
    examples += [Example(case, case.verdict == REFUSE) for case, _ in case_points]
    return examples, demo_bits


def _truth(ranked: Ranked, demo_bits: Sequence[int | None], case_bits: Sequence[int | None],
           case_results: Mapping[str, CandidateResult], has_cases: bool) -> dict[str, int]:
    """Per judged condition, the examples it holds at (bit k: example k)."""
    truth: dict[str, int] = {}
    for result in ranked.results:
        if result.status == "rejected" or (result.expression not in case_results and has_cases):
            continue
        elsewhere = case_results.get(result.expression)
        bits = [_bit(result.satisfied, b) for b in demo_bits]
        bits += [_bit(elsewhere.satisfied if elsewhere and elsewhere.status != "rejected" else 0, b)
                 for b in case_bits]
        truth[result.expression] = sum(1 << k for k, held in enumerate(bits) if held)
    return truth


def _tightened(truth: Mapping[str, int], policy: set[str], positive: int, negative: int, remaining: int,
               required: Sequence[str], learned: Sequence[Term], every: int) -> Table | list[str]:
    """The allowance that tightens the rule (`allowance_tables`): a table by category, else one k for every call
    (a list of at most one). Only a rule the other conditions give is tightened: alone an allowance would open
    an action whose labelled calls nothing else separates (one that stays refused, `options.unseen`)."""
    left = remaining & ~_refused_by(set(required), truth, remaining)
    if learned:
        left &= held_terms(learned, truth, every)
    flat = best_allowance({e: t for e, t in truth.items() if e in policy and allowance(e) >= 0}, positive,
                          negative, left)
    # one allowance for every call, unless only one looked up by category separates the calls it leaves
    table = table_of({e: t for e, t in truth.items() if e in policy}, positive, left, every, flat) \
        if positive and left & ~_refused_by(set(flat), truth, left) else None
    return table or flat


@dataclass(frozen=True)
class Outcome:
    """Where an action's judged conditions hold among its examples, and which the labels chose."""

    names: list[str]
    """Per example (bit k), how a rule's evidence names it."""
    truth: dict[str, int]
    positive: int
    negative: int
    from_labels: list[str]
    """The conditions the labels chose here (required, or in a separating term) that refuse calls labelled
    'refuse': what another action sharing them may adopt (`shared_rules`)."""

    def named(self, mask: int) -> list[str]:
        return [self.names[k] for k in _bits_of(mask)]


@dataclass
class Made:
    """An action's ranking as the labels change it: the rules chosen, their reasons and how each was decided."""

    ranked: Ranked
    index: OccurrenceIndex
    """The demonstrated calls among the demonstrations' points."""
    chosen: list[Cluster]
    reasons: dict[str, str]
    decided: dict[str, Decided]
    results: list[CandidateResult] = field(default_factory=list)
    evidence: dict[str, Any] = field(default_factory=dict)
    verdicts: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.results = self.results or list(self.ranked.results)
        self.evidence = self.evidence or dict(self.ranked.evidence)
        self.verdicts = self.verdicts or dict(self.ranked.verdicts)

    def adopt(self, expression: str, satisfied: int, reason: str) -> None:
        """One more rule, established, holding at the demonstrations' points `satisfied`."""
        if expression not in {r.expression for r in self.results}:
            self.results.append(CandidateResult(expression, "valid", None, satisfied))
        self.evidence[expression] = gather(satisfied, self.index)
        self.verdicts[expression] = "held" if not self.index.mask & ~satisfied else "tolerated"
        self.chosen.append(Cluster((Candidate(expression, "enumerate", satisfied),)))
        self.decided[expression] = "established"
        self.reasons[expression] = reason

    def separation(self, outcome: Outcome, made: Sequence[str], exempt: set[Point], unshown: bool) -> Separation:
        """The separation of these rules; a rule made here (`made`) that refuses a call to allow is assumed."""
        texts = [c.representative.expression for c in self.chosen]
        refuses = {e: outcome.named(outcome.negative & ~outcome.truth.get(e, 0)) for e in texts}
        wrong = {e: outcome.named(outcome.positive & ~outcome.truth.get(e, 0)) for e in texts}
        conflicts = [_conflict(e, wrong[e], refuses[e]) for e in made if wrong.get(e)]
        self.decided.update({e: "assumed" for e in made if wrong.get(e)})
        ranked = replace(self.ranked, results=self.results, chosen=self.chosen, reasons=self.reasons,
                         evidence=self.evidence, verdicts=self.verdicts, decided=self.decided)
        unrefused = outcome.named(outcome.negative & ~_refused_by(set(texts), outcome.truth, outcome.negative))
        return Separation(ranked, refuses, wrong, exempt, unrefused, unshown, conflicts, outcome, self)


def _conflict(rule: str, allowed: Sequence[str], refused: Sequence[str]) -> str:
    """A rule made from the labels that refuses calls to allow, in words (`Separation.conflicts`)."""
    def listed(names: Sequence[str]) -> str:
        counted = Counter(names)
        shown = [f"{n} x{c}" if c > 1 else n for n, c in list(counted.items())[:4]]
        more = len(counted) - len(shown)
        return ", ".join(shown) + (f" and {more} more" if more > 0 else "")
    return (f"conflict: `{rule}` refuses {len(allowed)} call(s) demonstrated or labelled 'allow' "
            f"({listed(allowed)}) to refuse {len(refused)} labelled 'refuse' ({listed(refused)}); no condition "
            f"separates both sides: assumed, review it")


def _kept(ranked: Ranked, truth: Mapping[str, int], positive: int, negative: int, unshown: bool = False
          ) -> tuple[set[str], dict[str, str]]:
    """The ranking's rules that allow every call to allow, assumed ones too (labels that never contradict a rule
    do not drop it); when each demonstrated call is labelled 'refuse' (`unshown`), only those that refuse a
    labelled call: they rest on those calls."""
    kept, notes = set(), {}
    for cluster in ranked.chosen:
        e = cluster.representative.expression
        held = truth.get(e)
        if held is None:
            continue
        if positive & ~held:
            notes[e] = f"dropped: refuses {(positive & ~held).bit_count()} call(s) labelled or demonstrated to allow"
        elif unshown and not negative & ~held:
            notes[e] = ("dropped: every demonstrated call it rests on is labelled 'refuse', and it refuses none of "
                        "them (evidence against it, not for)")
        else:
            kept.add(e)
    return kept, notes


MAX_REQUIRED = 3
CONDITION_COST = 0.5
"""A condition costs half a call to allow left refused: a rule as long as the calls it lists fits only them."""


def _required(truth: Mapping[str, int], positive: int, negative: int) -> list[str]:
    """Conditions that hold at every call to allow and refuse calls labelled 'refuse' ("nothing already flown"):
    the one refusing the most remaining calls first, then the shorter text, at most MAX_REQUIRED."""
    chosen: list[str] = []
    candidates = {e: t for e, t in truth.items() if not positive & ~t and negative & ~t and not _has_or(e)}
    while negative and len(chosen) < MAX_REQUIRED and candidates:
        best = min(candidates, key=lambda e: (-(negative & ~candidates[e]).bit_count(), _conditions(e), len(e)))
        if not negative & ~candidates[best]:
            break
        chosen.append(best)
        negative &= candidates.pop(best)
    return chosen


def _sources(examples: Sequence[Example], occurrences: Sequence[Point], case_points: Sequence[tuple[Case, Point]]
             ) -> list[tuple[Case | None, Point]]:
    """Per example, its labelled call (None for a demonstrated call no label names) and its point."""
    demonstrated = list(dict.fromkeys(occurrences))
    return [(e.case, demonstrated[k]) for k, e in enumerate(examples[:len(demonstrated)])] + \
        [(case, point) for case, point in case_points]


def _smallest(truth: Mapping[str, int], positive: int, negative: int, task_of: Sequence[str] | None = None,
              labelled: int | None = None) -> tuple[list[str], list[Term]]:
    """Required conditions and separating terms (`_cheapest`) of conditions that never refuse one task's calls
    labelled 'refuse' alone (`run_tasks.own_task`). `labelled`: every call labelled 'refuse', `negative` being
    those the rules kept leave allowed: the calls left may all be one task's, and a condition refusing only them
    passes for a reason although no other task's refused call shows it. So a rule of conditions each refusing
    calls of several tasks among `labelled` (what a leave-one-task-out choice still finds) is preferred wherever
    it leaves no more labelled calls on the wrong side than a rule judged on the calls left alone; else the
    latter is taken (with one labelled call a task, every reason refuses one task's calls)."""
    lenient = {e: t for e, t in truth.items() if not run_tasks.own_task(negative & ~t, negative, task_of)}
    wrong, found = _cheapest(lenient, positive, negative)
    if labelled is None or task_of is None:
        return found
    every = labelled | negative
    strict = {e: t for e, t in lenient.items() if not run_tasks.own_task(every & ~t, every, task_of)}
    shared_wrong, shared = _cheapest(strict, positive, negative)
    return shared if shared_wrong <= wrong else found


def _cheapest(truth: Mapping[str, int], positive: int, negative: int) -> tuple[int, tuple[list[str], list[Term]]]:
    """Required conditions (the first k of `_required`'s order) and the terms that separate what they leave:
    the k whose labelled calls left on the wrong side (calls to allow refused, calls labelled 'refuse' allowed),
    plus CONDITION_COST per condition, are fewest; with how many are on the wrong side. A call labelled 'refuse'
    that no condition holding at some call to allow refuses (`unseparable`) is left out of the terms' search: it
    stays allowed and is reported, and the terms still separate the others (one such label never costs the rule
    that refuses the rest)."""
    order = _required(truth, positive, negative)
    alone = unseparable(truth, positive, negative)
    best: tuple[tuple[float, int], int, list[str], list[Term]] | None = None
    for k in range(len(order) + 1):
        remaining = negative
        for e in order[:k]:
            remaining &= truth[e]
        for separated in dict.fromkeys((remaining & ~alone, remaining & ~alone & ~_shadows(truth, positive,
                                                                                           remaining))):
            terms = _terms(truth, positive, separated)
            allowed = held_terms(terms, truth, -1) if separated and terms else positive | remaining
            size = sum(_conditions(e) for e in order[:k]) + sum(_conditions(e) for t in terms for e in t)
            wrong = (positive & ~allowed).bit_count() + (remaining & allowed).bit_count()
            cost = (wrong + CONDITION_COST * size, size)
            if best is None or cost < best[0]:
                best = (cost, wrong, order[:k], terms)
    return (best[1], (best[2], best[3])) if best else (negative.bit_count(), ([], []))


def _shadows(truth: Mapping[str, int], positive: int, negative: int) -> int:
    """The calls labelled 'refuse' at which every condition holding at some call to allow holds too: a rule refuses
    one only by refusing that call to allow as well (`_smallest` weighs both)."""
    shadows = 0
    for p in _bits_of(positive):
        held = [t for t in truth.values() if (t >> p) & 1]
        for n in _bits_of(negative & ~shadows):
            if all((t >> n) & 1 for t in held):
                shadows |= 1 << n
    return shadows


def unseparable(truth: Mapping[str, int], positive: int, negative: int) -> int:
    """The calls labelled 'refuse' that every condition holding at some call to allow also allows: no rule made
    of these conditions refuses one of them without refusing every call to allow."""
    useful = [t for t in truth.values() if t & positive]
    return sum(1 << k for k in _bits_of(negative) if all((t >> k) & 1 for t in useful))


LIMIT_FORMS = re.compile(r" not in | != | < |\bany\(|\]\[[^\]]+\] == (?:'[^']*'|-?\d|None|True|False)")
"""What a permission does not say: a read missing, a value unequal, a date before, one logged value required."""


def _limits(truth: Mapping[str, int], negative: int, remaining: int) -> list[str]:
    """With nothing to allow, the conditions that refuse `remaining` of the calls labelled 'refuse' (`negative`)
    and state a limit or a requirement (at most n of a kind, every payment on the profile, the reservation read,
    nothing flown, booked within the day) that some of those calls meet, the one refusing the most first
    (`_required`). Nothing else bounds a rule here: `user_id not in ...` or `membership == 'regular'` refuse
    these calls and every other, and only a call to allow could show it, so none of those forms is learned; and
    a condition no labelled call meets (every saved passenger born after today) says no more than `False`."""
    return _required({e: t for e, t in truth.items() if t & negative and not LIMIT_FORMS.search(e)}, 0, remaining)


def _has_or(expression: str) -> bool:
    """A condition with a disjunction inside: a conjunct of the rule only if nothing simpler separates."""
    return any(isinstance(n, ast.BoolOp) and isinstance(n.op, ast.Or) for n in ast.walk(ast.parse(expression)))


def _conditions(expression: str) -> int:
    """How many comparisons (and bare truth tests) a condition makes: what 'as few conditions' counts."""
    return sum(isinstance(n, ast.Compare) for n in ast.walk(ast.parse(expression))) or 1


def _refused_by(kept: set[str], truth: Mapping[str, int], negative: int) -> int:
    refused = 0
    for e in kept:
        refused |= negative & ~truth[e]
    return refused


Term = tuple[str, ...]
"""A conjunction of one or two judged conditions."""


def _terms(truth: Mapping[str, int], positive: int, negative: int) -> list[Term]:
    """A greedy cover of the calls to allow by terms false at every call to refuse: one condition where one
    does, else two; the term that allows the most uncovered calls first, then the fewer conditions, then the
    conditions that hold at more calls to allow (a reason shared by every call, "nothing flown", before a
    correlate of the few, "one way"), then the shorter text. Empty when there is nothing to refuse or nothing
    separates. Never a price (`tool_conditions.scaled`): a price holds at every call to allow (`_required`), and
    prices that each fit a few of them are counts fitted one by one."""
    if not negative or not positive:
        return []
    useful = sorted((e for e, t in truth.items() if t & positive and not arithmetic(e)),
                    key=lambda e: (-(truth[e] & positive).bit_count(), (truth[e] & negative).bit_count(), len(e)))
    terms: dict[Term, int] = {(e,): truth[e] for e in useful if not truth[e] & negative}
    paired = [e for e in useful if truth[e] & negative][:MAX_PAIRED]
    for n, a in enumerate(paired):
        for b in paired[n + 1:]:
            both = truth[a] & truth[b]
            if both & positive and not both & negative:
                terms.setdefault((a, b), both)
    chosen: list[Term] = []
    uncovered = positive
    while uncovered and len(chosen) < MAX_TERMS and terms:
        best = min(terms, key=lambda t: (-(terms[t] & uncovered).bit_count(), sum(_conditions(e) for e in t),
                                         -sum((truth[e] & positive).bit_count() for e in t), len(_text([t]))))
        if not terms[best] & uncovered:
            break
        chosen.append(best)
        uncovered &= ~terms.pop(best)
    return chosen


def _text(terms: Sequence[Term]) -> str:
    """`a and b or c`, each part in parentheses where Python would read it otherwise."""
    def part(e: str, inside_and: bool) -> str:
        node = ast.parse(e, mode="eval").body
        loose = isinstance(node, ast.IfExp | ast.Lambda | ast.NamedExpr) or (
            inside_and and isinstance(node, ast.BoolOp) and isinstance(node.op, ast.Or))
        return f"({e})" if loose else e
    if len(terms) == 1 and len(terms[0]) == 1:
        return terms[0][0]
    conjunctions = [" and ".join(part(e, len(t) > 1) for e in t) for t in terms]
    return " or ".join(f"({c})" if len(t) > 1 and len(terms) > 1 else c
                       for c, t in zip(conjunctions, terms, strict=True))




def _index(points: Sequence[Point], point: Point) -> int | None:
    try:
        return points.index(point)
    except ValueError:
        return None


def _bit(satisfied: int, bit: int | None) -> bool:
    return bit is not None and bool((satisfied >> bit) & 1)


def _bits_of(mask: int) -> list[int]:
    return [k for k in range(mask.bit_length()) if (mask >> k) & 1]


def _name(example: Example) -> str:
    return example.case.name if example.case else "a demonstrated call"
