"""Prior rules: what a tenant learned for its other services, as candidates for a new one.

The rules still wrong after inference are the ones a service's demonstrations cannot teach: an action never or
thinly demonstrated, a correlate the calls never separate from the requirement, the polarity of a failure. A
team's services share their dialog acts, so the rules it already learned for those acts are the best guess
there. They are candidates, never verdicts: each runs on this request's demonstrations like any candidate (the
sandbox judges it), and one that does not hold at the demonstrated calls is refuted. Only where the
demonstrations do not decide does a surviving prior win (`prefer`), and its rule says `decided: transferred`
with its sources.

Several sources are several votes: where they disagree on an action (one service learned `not
self.query_success`, another `self.query_success is None`), the surviving priors most sources name are
preferred; ties are all kept (a conjunction two sources share).
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

from precond.engine.candidates.library import PREFIX, SIGNED_SOURCE, Library
from precond.engine.judging.cautious import Choice
from precond.engine.judging.ranking import ActionEvidence, Candidate, Cluster
from precond.engine.spec import Spec, as_error
from precond.programs import checks
from precond.programs.checks import normal
from precond.sandbox.types import CandidateResult
from precond_client.schemas import Decided, InferOptions, Verdict
from precond_client.schemas.errors import InvalidInput

SURVIVING: tuple[Verdict, ...] = ("held", "tolerated", "chance")
"""Verdicts of a prior that holds at the demonstrated calls (a 'chance' one is common elsewhere too: the calls
cannot refute it, and the other services' evidence is what speaks for it)."""
SURVIVING_THIN: tuple[Verdict, ...] = (*SURVIVING, "thin")


@dataclass
class Prior:
    """One prior rule for one action, with every source that names it (canonical text)."""

    expression: str
    sources: list[str] = field(default_factory=list)


@dataclass
class Priors:
    """Per action of this request: the applicable prior rules by canonical text, and why others were dropped."""

    rules: dict[str, dict[str, Prior]] = field(default_factory=dict)
    dropped: dict[str, list[str]] = field(default_factory=dict)

    def expressions(self, action: str) -> list[str]:
        return [p.expression for p in self.rules.get(action, {}).values()]

    def source_of(self, action: str, expression: str) -> str | None:
        prior = self.rules.get(action, {}).get(normal(expression))
        return ", ".join(prior.sources) if prior else None


def collect(options: InferOptions, spec: Spec, actions: Sequence[str], demonstrations: Sequence[str],
            library: Library | None = None) -> Priors:
    """The priors of a request that apply to its actions. A rule that is not one expression, or that calls
    something, is bad input (422 naming it); one that names what this spec does not define, or an action this
    request does not infer, does not apply and is dropped with a reason. The shipped library's sources
    (`engine.library`) join for the actions the request's own priors leave alone; a library rule this spec
    cannot read is left out without a warning (the tenant sent nothing wrong)."""
    if options.prior_sets:
        raise InvalidInput("prior_sets are resolved by the service: send their rules in options.prior_sources here",
                           field="options.prior_sets")
    sources = options.priors()
    try:
        checks.check_prior_rules([(where, table) for _, where, table in sources])
    except checks.ProgramProblem as exc:
        raise as_error(exc) from exc
    literals = _literals([spec.source, *demonstrations])
    attributes = _attributes(spec.tree)
    found = Priors()
    own: dict[str, list[str]] = {}
    for _, _, table in sources:
        for action, rules in table.items():
            own.setdefault(action, []).extend(rules)
    shipped = (library or Library()).for_spec(actions, own) if options.library else []
    for source, where, table in [*sources, *((name, "", rules) for name, rules in shipped)]:
        for action, rules in table.items():
            if action not in actions:  # another service's action, or one this request does not infer
                continue
            for rule in rules:
                why = _undefined(rule, _parameters(spec, action), attributes, literals)
                if why is not None:
                    if where:
                        found.dropped.setdefault(action, []).append(f"{rule!r} from {source}: {why}")
                    continue
                prior = found.rules.setdefault(action, {}).setdefault(normal(rule), Prior(rule.strip()))
                if source not in prior.sources:
                    prior.sources.append(source)
    return found


def _parameters(spec: Spec, action: str) -> tuple[str, ...]:
    method = spec.methods[action]
    return (*method.positional, *method.kwonly)


def _undefined(rule: str, params: Sequence[str], attributes: set[str], literals: set[object]) -> str | None:
    """What the rule names that this spec does not define: an argument the action does not take, an attribute no
    class sets, a key (a slot, an intent) neither the spec nor a demonstration mentions; a constant rule (the
    placeholder `False` of a never-demonstrated action) says nothing learned."""
    tree = ast.parse(rule.strip(), mode="eval")
    if isinstance(tree.body, ast.Constant):
        return "a constant says nothing learned about the action"
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id != "self" and node.id not in params and node.id != "None":
            return f"names {node.id!r}, which the action does not take"
        if isinstance(node, ast.Attribute) and node.attr not in attributes:
            return f"names the attribute {node.attr!r}, which no class of this spec sets"
        if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) \
                and isinstance(node.slice.value, str) and node.slice.value not in literals:
            return f"names {node.slice.value!r}, which neither the spec nor a demonstration mentions"
    return None


def _attributes(tree: ast.Module) -> set[str]:
    """Every `self.<name>` the spec assigns, and its methods' names."""
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            names.add(node.attr)
        elif isinstance(node, ast.FunctionDef):
            names.add(node.name)
    return names


def _literals(programs: Sequence[str]) -> set[object]:
    found: set[object] = set()
    for program in programs:
        try:
            tree = ast.parse(program)
        except (SyntaxError, ValueError, RecursionError):
            continue
        found |= {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    return found


def state_read(expression: str) -> frozenset[tuple[str, object]]:
    """The state a condition is about: its outermost attributes, with a literal key where it subscripts one
    (`self.user.informed_slot['city']` reads ('informed_slot', 'city'); `self.user` is only the way there)."""
    try:
        tree = ast.parse(expression, mode="eval")
    except (SyntaxError, ValueError, RecursionError):
        return frozenset()
    inner = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    keyed = {id(n.value): n for n in ast.walk(tree) if isinstance(n, ast.Subscript)}
    found: set[tuple[str, object]] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and id(node) not in inner:
            sub = keyed.get(id(node))
            key = sub.slice.value if sub is not None and isinstance(sub.slice, ast.Constant) else None
            found.add((node.attr, key))
    return frozenset(found)


def preferred(priors: Sequence[Prior], results: Mapping[str, CandidateResult], verdicts: Mapping[str, Verdict],
              evidence: ActionEvidence, demonstrated: bool, sparse: bool) -> list[Candidate]:
    """The surviving priors most sources name: for a never-demonstrated action every prior the sandbox could
    judge survives; otherwise one that held at every demonstrated call (on thin evidence too). Equally named
    priors that no point satisfies together (one service guessed `self.query_success is None`, another
    `self.query_success is not None`) are no majority reading: neither is preferred."""
    mask = evidence.occurrence_mask
    fates = SURVIVING_THIN if sparse else SURVIVING
    alive: list[tuple[Prior, CandidateResult]] = []
    for prior in priors:
        result = results.get(prior.expression)
        if result is None or result.status == "rejected":
            continue
        if demonstrated and (verdicts.get(prior.expression) not in fates or mask & ~result.satisfied):
            continue
        alive.append((prior, result))
    best = max((len(p.sources) for p, _ in alive), default=0)
    top = [(p, r) for p, r in alive if len(p.sources) == best]
    clashing = {i for i, (p, _) in enumerate(top) for j, (q, _) in enumerate(top)
                if i != j and contradict(p.expression, q.expression)}
    return [Candidate(p.expression, "prior", r.satisfied) for i, (p, r) in enumerate(top) if i not in clashing]


ANSWERS = (None, True, False)
"""The values an answer of the agent's own service takes (`query_success`: not asked, yes, no)."""


def contradict(a: str, b: str) -> bool:
    """Whether two rules about one value (`self.query_success is None`, `self.query_success is not None`) hold
    for none of `ANSWERS` together. Read from their syntax, never run: rules of other services are untrusted
    and the sandbox is for judging them on states; a rule this cannot read contradicts nothing."""
    state = state_read(a)
    if len(state) != 1 or state_read(b) != state:
        return False
    try:
        left, right = (ast.parse(e.strip(), mode="eval").body for e in (a, b))
    except (SyntaxError, ValueError, RecursionError):
        return False
    both = [(_value(left, v), _value(right, v)) for v in ANSWERS]
    return all(x is not None and y is not None for x, y in both) and not any(x and y for x, y in both)


def _value(node: ast.expr, value: bool | None) -> bool | None:
    """`node` with its one state read as `value`; None where it is not a test this reads (a call, an operator)."""
    if isinstance(node, ast.Attribute | ast.Subscript):
        return bool(value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
        inner = _value(node.operand, value)
        return None if inner is None else not inner
    if isinstance(node, ast.BoolOp):
        parts = [_value(v, value) for v in node.values]
        if any(p is None for p in parts):
            return None
        return all(parts) if isinstance(node.op, ast.And) else any(parts)
    if isinstance(node, ast.Compare) and len(node.ops) == 1 and isinstance(node.left, ast.Attribute | ast.Subscript) \
            and isinstance(node.comparators[0], ast.Constant) and node.comparators[0].value in ANSWERS:
        other, op = node.comparators[0].value, node.ops[0]
        if isinstance(op, ast.Is | ast.Eq):
            return value is other
        if isinstance(op, ast.IsNot | ast.NotEq):
            return value is not other
    return None


def support(priors: Sequence[Prior]) -> dict[str, int]:
    """How many sources name each prior, by its expression."""
    return {p.expression: len(p.sources) for p in priors}


def prefer(choice: Choice, chosen_priors: Sequence[Candidate], support: Mapping[str, int], sparse: bool,
           params: Sequence[str] = (), common: frozenset[str] = frozenset()) -> Choice:
    """The action's rules with the preferred priors where the demonstrations do not decide.

    Never demonstrated: the priors replace the zero-shot guess. Thinly demonstrated: they replace the guesses
    about the state they read; the other assumed guesses stay (another service's rule says what it requires,
    not that this one's confirmation does not need the slots it confirms). Otherwise:
    * where the demonstrations established a disjunction of triggers, the priors' alternatives join it
      (`_alternatives`);
    * a kept rule a prior names too becomes the prior's (transferred: two services agree);
    * an established rule about the state a prior is about (`state_read`: `self.query_success is not None`
      beside the prior `not self.query_success`) is another reading of it, which the calls cannot tell apart:
      the prior's reading replaces it (and a rule the demonstrations and a prior agree on settles the
      reading of its state: no other prior, no other established rule about it), unless the prior is
      `common` here (not separated from chance at this service's calls: they decide, and it is not their
      reading);
    * assumed rules stay unless a prior reads their state: another service's rule says what it requires,
      not that this one's correlates are not required;
    * a prior the ranking passed over (a phase, a common fact) joins when two or more sources name it.
    """
    if not chosen_priors:
        return choice
    if sparse:
        return _prefer_thin(choice, chosen_priors)
    choice, chosen_priors = _alternatives(choice, chosen_priors, params)
    if not chosen_priors:
        return choice
    by_text = {normal(c.expression): c for c in chosen_priors}
    own = {normal(c.representative.expression): c for c in choice.chosen}
    agreed = [by_text[t] for t in by_text if t in own]
    settled = [state_read(c.expression) for c in agreed]
    others = [c for c in chosen_priors if normal(c.expression) not in own
              and not any(_about(state_read(c.expression), s) for s in settled)]
    readings = [c for c in others if c.expression not in common
                and any(choice.decided.get(k.representative.expression) == "established"
                        and _about(state_read(k.representative.expression), state_read(c.expression))
                        for k in choice.chosen)]
    joining = [c for c in others if c not in readings and support.get(c.expression, 0) >= 2]
    transferred = [*agreed, *readings, *joining]
    if not transferred:
        return choice
    replaced = {normal(c.expression) for c in agreed}
    states = [*settled, *(state_read(r.expression) for r in readings)]
    kept = [c for c in choice.chosen if choice.decided.get(c.representative.expression) in ("established", "assumed")
            and normal(c.representative.expression) not in replaced
            and not any(_about(state_read(c.representative.expression), s) for s in states)]
    decided: dict[str, Decided] = {c.representative.expression: choice.decided[c.representative.expression]
                                   for c in kept}
    decided.update({c.expression: "transferred" for c in transferred})
    notes = {e: n for e, n in choice.notes.items() if e in decided}
    return replace(choice, chosen=[*kept, *(Cluster((c,)) for c in transferred)], decided=decided,
                   notes={**notes, **_notes(transferred)})


def _prefer_thin(choice: Choice, chosen_priors: Sequence[Candidate]) -> Choice:
    """A thinly demonstrated (or never demonstrated) action: the priors replace the guesses about the state they
    read, and the other established or assumed rules stay."""
    own_kept = [
        c for c in choice.chosen if choice.decided.get(c.representative.expression) in ("established", "assumed")
        and not any(_about(state_read(c.representative.expression), state_read(p.expression))
                    for p in chosen_priors)]
    prior_decided: dict[str, Decided] = {c.expression: "transferred" for c in chosen_priors}
    return replace(choice, chosen=[*own_kept, *(Cluster((c,)) for c in chosen_priors)],
                   decided={**{c.representative.expression: choice.decided[c.representative.expression]
                               for c in own_kept}, **prior_decided},
                   notes={**{e: n for e, n in choice.notes.items()
                             if any(e == c.representative.expression for c in own_kept)},
                          **_notes(chosen_priors)})


def _about(state: frozenset[tuple[str, object]], other: frozenset[tuple[str, object]]) -> bool:
    """Whether a rule reading `state` is about (part of) what `other` reads."""
    return bool(state) and state <= other


def _notes(transferred: Sequence[Candidate]) -> dict[str, str]:
    return {c.expression: "transferred: a prior rule that held at every demonstrated call, preferred where the "
            "demonstrations do not decide" for c in transferred}


MAX_MERGED_TERMS = 6
"""A kept disjunction with the priors' alternatives: at most this many terms (twice the cover's bound)."""


def _alternatives(choice: Choice, chosen_priors: Sequence[Candidate], params: Sequence[str]
                  ) -> tuple[Choice, list[Candidate]]:
    """Where the demonstrations established a disjunction of single conditions (the calls were enabled by one
    of several triggers: "anything else?" after a "no, thanks" or after a failure), a prior of a single
    condition or a disjunction of them is another service's list of what enables the same act: its terms
    join the disjunction as alternatives, not the conjunction (conjoined, a trigger that enabled the act
    elsewhere would refuse it wherever another alternative enabled it). Several established disjunctions
    are several such lists and become one. A term about the action's own arguments is a requirement on what
    is asked, not an alternative trigger: such a prior is left to the other cases, as is a conjunction.
    Returns the choice and the priors left for the other cases."""
    own = [c for c in choice.chosen if choice.decided.get(c.representative.expression) == "established"
           and len(_terms(c.representative.expression)) > 1]
    alternatives = [c for c in chosen_priors if _terms(c.expression)
                    and not any(_names(t) & set(params) for t in _terms(c.expression))]
    if not own or not alternatives:
        return choice, list(chosen_priors)
    merged: list[str] = []
    for expression in [*(c.representative.expression for c in own), *(c.expression for c in alternatives)]:
        for term in _terms(expression):
            if normal(term) not in {normal(t) for t in merged} and len(merged) < MAX_MERGED_TERMS:
                merged.append(term)
    if len(own) == 1 and len(merged) == len(_terms(own[0].representative.expression)):
        return choice, list(chosen_priors)  # nothing to join: the other cases read the priors
    expression = " or ".join(merged)
    satisfied = 0
    for c in own:
        satisfied |= c.satisfied
    for p in alternatives:
        satisfied |= p.satisfied
    joined = Cluster((Candidate(expression, own[0].representative.source, satisfied),))
    replaced = {c.representative.expression for c in own}
    chosen = [joined if c is own[0] else c for c in choice.chosen if c is own[0] or c not in own]
    decided: dict[str, Decided] = {e: d for e, d in choice.decided.items() if e not in replaced}
    decided[expression] = "established"
    listed = ", ".join(repr(c.expression) for c in alternatives)
    notes = {e: n for e, n in choice.notes.items() if e not in replaced}
    notes[expression] = (f"{choice.notes.get(own[0].representative.expression, 'a disjunction of triggers')}; "
                         f"joined by the prior rules' alternatives ({listed})")
    return replace(choice, chosen=chosen, decided=decided, notes=notes), [
        c for c in chosen_priors if c not in alternatives]


def _names(expression: str) -> set[str]:
    try:
        return {n.id for n in ast.walk(ast.parse(expression, mode="eval")) if isinstance(n, ast.Name)}
    except (SyntaxError, ValueError, RecursionError):
        return set()


def _terms(expression: str) -> list[str]:
    """The terms of a disjunction of single conditions (one condition: itself); [] for anything else (a
    conjunction inside, a tool call's credential sets)."""
    try:
        node = ast.parse(expression.strip(), mode="eval").body
    except (SyntaxError, ValueError, RecursionError):
        return []
    values = node.values if isinstance(node, ast.BoolOp) and isinstance(node.op, ast.Or) else [node]
    if any(isinstance(n, ast.BoolOp) for v in values for n in ast.walk(v)):
        return []
    return [ast.unparse(v) for v in values]


def signed(choice: Choice, prior: Priors, action: str, results: Sequence[CandidateResult],
           verdicts: Mapping[str, Verdict]) -> Choice:
    """The library's signed notices (`library.SIGNED`) join the kept rules, demonstrated or not, unless a call
    refutes them: "Sorry, that failed" needs a failure result though every demonstrated one also read `not
    self.query_success`, which holds before anything was asked."""
    source = PREFIX + SIGNED_SOURCE
    by_text = {r.expression: r for r in results}
    kept = {c.representative.expression for c in choice.chosen}
    added: list[Cluster] = []
    for rule in prior.rules.get(action, {}).values():
        result = by_text.get(rule.expression)
        if source not in rule.sources or rule.expression in kept or result is None or result.status == "rejected" \
                or verdicts.get(rule.expression) == "refuted":
            continue
        added.append(Cluster((Candidate(rule.expression, "prior", result.satisfied),)))
    if not added:
        return choice
    decided: dict[str, Decided] = {**choice.decided, **{c.representative.expression: "transferred" for c in added}}
    return replace(choice, chosen=[*choice.chosen, *added], decided=decided)
