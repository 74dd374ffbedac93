"""The cautious criterion (the default): rules that hold up in the states a guard exists for.

The paper's criteria are judged on test dialogs from the same generator as the demonstrations, where a rule
merely correlated with the true requirement scores perfectly. A guard is consulted where that correlation
breaks: the user confirms before their identity was checked, the search is asked for before the intent was
stated. The demonstrations cannot tell a requirement from a correlate there, so this criterion does not pick
the permissive side silently. For each action it keeps:

1. *Established* rules: the conditions the observations since the agent's previous turn made true or renewed
   (`ranking.enabling_rate` with `precond/engine/judging/freshness.py`), among themselves subsumption-minimal (a
   trigger that
   a phase subsumes on the demonstrated points is still the trigger: a success notice follows the success,
   not the confirmation before it). Conditions on the action's own arguments count as established.
2. When no single condition is such a trigger at the calls, or the triggers leave some calls unexplained (they
   held there as a phase): a *disjunction* of triggers, found by a greedy cover of the calls with the
   conditions made true before them ("anything else?" after a "no, thanks", after a declined offer or after
   a failure); for a tool call each term is a conjunction (two alternative credential sets). A term is a
   positive fact, or a negative one that an observation since the agent's previous turn wrote (the service
   answered no: news, unlike "nothing was asked yet"). A trigger that at every call it enabled only re-read
   what another term states about the same state (`query_success is not None` beside `not query_success`)
   is replaced by the disjunction.
3. *Assumed* rules for tool calls (an action whose calls a service answers, like a search or a card block):
   every positive fact (a slot informed, an identity verified, an intent stated: `polarity`) that held at
   every demonstrated call, though it was true long before (a phase), true almost everywhere (not separated
   from chance) or implied by another rule *on the demonstrated points* (which is not implication). Nothing
   shows the call can happen without it, so the guard keeps it and says so; a reviewer can drop it.
   A dialog act gets them only about what it speaks of, when it speaks of what the user gave (`spoken_of`:
   a confirmation of the city needs the city; an offer of what a search found does not need the user's
   words): acting on any other phase there costs a re-ask, not a blocked card, and dialog acts are what an
   assistant says most (docs/results.md measures both sides).
4. *Behind a yes*: where a flag of the other party (`self.user.affirmed`) was made true right before every call
   of a tool call, it answers the agent's confirmation, so the facts of that party about the slots the
   confirmation named are not assumed (`behind_trigger`, `confirmed`: `ActionEvidence.confirmed`, what the
   dialog's confirmations and the answered offer named; a yes that answered none covers nothing; named in the
   warning, `Choice.behind`); the agent's own state (an identity check, a search's success) is the service's
   answer, which no yes replaces, and stays assumed. What else held at each call is searched for a disjunction
   (`hidden_disjunction`: refills left or the doctor's approval, neither at every refill): kept, assumed, where
   a demonstration shows the yes without it and no call, or where its terms are the agent's own state
   (`answered`: what the back-end said, which no yes overrides); otherwise offered among the dropped candidates
   for a reviewer.

Actions demonstrated too thinly to learn from get the positive facts their few calls share, assumed
(`thin_rules`: for a tool call every one but those behind a yes, for a dialog act what enabled it and what it
speaks of); never-demonstrated actions are `options.unseen`'s business (engine.engine).
"""

from __future__ import annotations

import ast
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from precond.engine.judging.evidence import CHANCE_ALPHA, Evidence
from precond.engine.judging.freshness import ANY, Access, reads, refreshed
from precond.engine.judging.ranking import (
    ActionEvidence,
    Candidate,
    Cluster,
    cluster,
    enabled_at,
    enabling_rate,
    informative,
    subsumption,
)
from precond.sandbox.types import Point
from precond_client.schemas import Decided

MAX_TERMS = 3
MAX_DISJUNCTION_ATOMS = 400  # conditions the cover looks at; more are left out and the report says so


@dataclass(frozen=True)
class Choice:
    """What an action keeps and how each kept rule was decided (keyed by its expression)."""

    chosen: list[Cluster]
    decided: dict[str, Decided] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)  # expression -> why it was kept, in words
    search: str = ""  # the disjunction search stopped at its bound: what it looked at, in words
    unguarded: list[str] = field(default_factory=list)  # assumed rules a conversational act does not keep
    behind: list[str] = field(default_factory=list)  # the other party's facts its "yes" before every call covers
    offered: list[tuple[Cluster, str]] = field(default_factory=list)  # composed alternatives not kept, and why


def polarity(expression: str) -> str:
    """'positive': asserts that something was established (a flag set, a slot informed, a result present, an
    argument among what was offered); 'negative': that something has not happened (yet), or is absent."""
    try:
        node = ast.parse(expression, mode="eval").body
    except (SyntaxError, RecursionError, ValueError):
        return "negative"
    return "negative" if _negated(node) else "positive"


def _negated(node: ast.expr) -> bool:
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
        return True
    if isinstance(node, ast.BoolOp):
        return any(_negated(v) for v in node.values)
    if isinstance(node, ast.Compare):
        return any(isinstance(op, ast.NotEq | ast.NotIn) for op in node.ops) or any(
            isinstance(op, ast.Is) and isinstance(c, ast.Constant) and c.value is None
            for op, c in zip(node.ops, node.comparators, strict=True))
    return False


def triggers(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    index = {point: bit for bit, point in enumerate(evidence.points)}
    enabled = [c for c in clusters if enabling_rate(c, evidence, index) > 0]
    minimal = subsumption(enabled, evidence.occurrence_mask)
    valued = {access for c in minimal if not _presence(c.representative.expression)
              for access in reads(c.representative.expression)}
    return [c for c in minimal if not (_presence(c.representative.expression)
                                       and reads(c.representative.expression) <= valued)]


def _presence(expression: str) -> bool:
    """`x is None` / `x is not None`: that an answer exists, beside a trigger that tests what it said (`not x`),
    which carries the news; the presence test alone would refuse before anything was asked."""
    node = _parsed(expression)
    return (isinstance(node, ast.Compare) and len(node.ops) == 1 and isinstance(node.ops[0], ast.Is | ast.IsNot)
            and isinstance(node.comparators[0], ast.Constant) and node.comparators[0].value is None)


def choose(clusters: Sequence[Cluster], common: Sequence[Cluster], atoms: Sequence[Cluster],
           evidence: ActionEvidence, tool_call: bool, conversational: bool = False, follow_up: bool = False
           ) -> Choice:
    """`clusters`: the candidates that passed validation (triggers come from these); `common`: those plus the
    ones true almost everywhere (not separated from chance), which a tool call may still require; `atoms`:
    every judged candidate, for the disjunction's terms (each alone is refuted by the calls the others cover).
    A `conversational` act (not among `options.guarded`: a goodbye, "anything else?") keeps only what its
    calls establish: refusing it where a correlate fails costs the user a dead end, allowing it costs little,
    so the assumed rules are named (`Choice.unguarded`), not kept; a `follow_up` offer ("anything else?") keeps
    that its agent's request was answered (`_conversational`)."""
    chosen = triggers(clusters, evidence)
    decided: dict[str, Decided] = {c.representative.expression: "established" for c in chosen}
    notes: dict[str, str] = {}
    search = ""
    if not chosen or unexplained(chosen, evidence):
        found, terms, note, cut = disjunction(atoms, evidence, tool_call)
        weak = restated(chosen, terms, evidence) if found is not None else []
        if found is not None and (weak or not chosen):  # beside triggers that stay, it would only repeat them
            chosen = [c for c in chosen if c not in weak] + [found]
            decided = {c.representative.expression: "established" for c in chosen}
            notes[found.representative.expression] = note + (
                f"; it replaces {', '.join(repr(c.representative.expression) for c in weak)}, which only "
                "re-read at some calls what the disjunction's terms made true there" if weak else "")
        if cut:
            search = f"disjunction search bounded: {note}"
    kept = {c.satisfied for c in chosen}
    extra = assumed(common, evidence, kept) if tool_call else spoken_of(common, atoms, evidence, kept)
    assenting = behind_trigger(chosen, evidence) if tool_call else frozenset()
    behind = [c for c in extra if assenting and parties(c.representative.expression) <= assenting
              and confirmed(c.representative.expression, evidence)]
    extra = [c for c in extra if c not in behind]
    offered: list[tuple[Cluster, str]] = []
    if assenting:
        found, witnessed, why = hidden_disjunction(atoms, chosen, evidence, assenting)
        if found is not None and (witnessed or answered(found)):
            extra.append(found)
            notes[found.representative.expression] = why
        elif found is not None:
            offered.append((found, why))
    if conversational:
        return _conversational(chosen, decided, notes, search, extra, common, evidence, follow_up)
    for c in extra:
        chosen.append(c)
        decided[c.representative.expression] = "assumed"
    return Choice(chosen, decided, notes, search, behind=[c.representative.expression for c in behind],
                  offered=offered)


def behind_trigger(chosen: Sequence[Cluster], evidence: ActionEvidence) -> frozenset[str]:
    """The objects of the other party (`self.user`) one of whose flags, made true since the agent's previous turn,
    came before every demonstrated call: the user's "yes" before each booking. Empty when there is none."""
    index = {point: bit for bit, point in enumerate(evidence.points)}
    found: set[str] = set()
    for c in chosen:
        owners = parties(c.representative.expression)
        if _flag(c.representative.expression) and "self" not in owners \
                and evidence.occurrences and all(enabled_at(c, evidence, index)):
            found |= owners
    return frozenset(found)


ANY_SLOT = "*"
"""In `ActionEvidence.confirmed`: a confirmation that names no slot (`ASK_CONFIRM_BOOKING()`) asks about all of it."""


def confirmed(expression: str, evidence: ActionEvidence) -> bool:
    """Whether the yes before every call covers this fact of the party that said it: the agent's confirmation in
    the turn right before each call's observations named the fact's slot (`CONFIRM('address')` covers
    `informed_slot['address']`), or named none; a fact about no slot (an intent, `selected`) it covers whole. A yes
    that answered no confirmation covers nothing, and a slot no confirmation named stays required: the user who
    says yes to an offer before giving the address."""
    asked = [evidence.confirmed.get((occ.demo, occ.position), frozenset()) for occ in evidence.occurrences]
    if not asked or not all(asked):
        return False
    keys = {k for _, k in _lookups(expression)} & evidence.slots
    return all(ANY_SLOT in a or keys <= a for a in asked)


def _flag(expression: str) -> bool:
    """`self.user.affirmed`: a flag of an object, not an entry of a mapping (`informed_slot['date']`, the last
    of the slots given) nor a comparison."""
    node = _parsed(expression)
    while isinstance(node, ast.Attribute):
        node = node.value
    return isinstance(node, ast.Name) and node.id == "self" and "." in expression


def parties(expression: str) -> frozenset[str]:
    """Whose state a condition reads: the object each outermost attribute is read from (`self.user` in
    `self.user.informed_slot['city']`, `self` in `self.query_success is None`)."""
    node = _parsed(expression)
    if node is None:
        return frozenset()
    inner = {id(n.value) for n in ast.walk(node) if isinstance(n, ast.Attribute)}
    return frozenset(ast.unparse(n.value) for n in ast.walk(node)
                     if isinstance(n, ast.Attribute) and id(n) not in inner)


def hidden_disjunction(atoms: Sequence[Cluster], chosen: Sequence[Cluster], evidence: ActionEvidence,
                       assenting: frozenset[str]) -> tuple[Cluster | None, bool, str]:
    """Behind a "yes" that came before every call, what else held at each: a greedy cover of the calls by the
    positive facts not of the party that said yes (a refill with refills left at some calls, with the doctor's
    approval at the others), each term failing at some call (one that held at all of them is assumed alone),
    at most MAX_TERMS terms; None unless two or more terms cover every call. Also whether the demonstrations
    witness it: a state where the kept rules held, the action was not taken and no term held (the patient said
    yes, no refill was left, the doctor said no, and the refill did not follow); and what happened, in words.
    Witnessed, the disjunction is kept (assumed); otherwise it is offered among the dropped candidates."""
    index = {point: bit for bit, point in enumerate(evidence.points)}
    bits = [index.get(occ) for occ in evidence.occurrences]
    if not bits or any(b is None for b in bits):
        return None, False, ""
    calls = set(range(len(bits)))
    held = {c.satisfied: {k for k, b in enumerate(bits) if b is not None and (c.satisfied >> b) & 1} for c in atoms}
    usable = [c for c in atoms if polarity(c.representative.expression) == "positive"
              and not _presence(c.representative.expression)
              and not parties(c.representative.expression) <= assenting
              and held[c.satisfied] and held[c.satisfied] != calls][:MAX_DISJUNCTION_ATOMS]
    uncovered, terms = set(calls), list[Cluster]()
    while uncovered and len(terms) < MAX_TERMS:
        best = max(usable, key=lambda c: (len(held[c.satisfied] & uncovered), -len(c.representative.expression)),
                   default=None)
        if best is None or not held[best.satisfied] & uncovered:
            break
        terms.append(best)
        uncovered -= held[best.satisfied]
    if uncovered or len(terms) < 2:
        return None, False, ""
    expression = " or ".join(t.representative.expression for t in terms)
    satisfied = 0
    for t in terms:
        satisfied |= t.satisfied
    kept = (1 << len(evidence.points)) - 1
    for c in chosen:
        kept &= c.satisfied
    witnessed = bool(kept & ~evidence.occurrence_mask & ~satisfied)
    what = "a disjunction behind the trigger: at every call one of its terms held, none at all of them"
    if witnessed:
        why = f"{what}; the demonstrations show the trigger without any term and no call; assumed (review it)"
    elif all(answered(t) for t in terms):
        why = f"{what}; its terms are what the agent's back-end answered, which no yes overrides; assumed (review it)"
    else:
        why = (f"dropped: {what}; no demonstration shows the trigger without any term and no call, so nothing tells "
               "it from a coincidence (a reviewer may keep it)")
    return Cluster((Candidate(expression, terms[0].representative.source, satisfied),)), witnessed, why


def answered(c: Cluster) -> bool:
    """A condition on the agent's own state alone (`self.has_refills or self.doctor_approved`): what its back-end
    answered (refills left, an approval), which the other party's yes cannot override."""
    return parties(c.representative.expression) == frozenset({"self"})


def _conversational(chosen: Sequence[Cluster], decided: Mapping[str, Decided], notes: dict[str, str], search: str,
                    extra: Sequence[Cluster], common: Sequence[Cluster], evidence: ActionEvidence, follow_up: bool
                    ) -> Choice:
    """A conversational act keeps its triggers but the agent's own answer (`own_answer`) and names the rest.

    A `follow_up` offer ("anything else?") asks whether the user needs more once the agent served a request, so
    where nothing the other party did explains its calls (a log without the user's acts) it keeps the presence
    of that answer (`self.query_success is not None`) where it held at every call, whichever answers the calls
    followed: refused only before anything was asked, never after a failure. Where the user's thanks or
    decline enabled it, those are its rule, before anything was asked too."""
    own = [c for c in chosen if own_answer(c.representative.expression)]
    kept = [c for c in chosen if c not in own]
    out: dict[str, Decided] = {c.representative.expression: decided[c.representative.expression] for c in kept
                               if c.representative.expression in decided}
    if follow_up and not kept:
        for c in served((*own, *extra, *common), evidence):
            out[c.representative.expression] = decided.get(c.representative.expression, "assumed")
            kept.append(c)
    named = [c.representative.expression for c in (*own, *extra) if c not in kept]
    return Choice(kept, out, {e: n for e, n in notes.items() if e in out}, search, list(dict.fromkeys(named)))


def served(clusters: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    """What a follow-up offer keeps: the first presence test of the agent's own answer that held at every call."""
    mask = evidence.occurrence_mask
    for c in clusters:
        if mask and not mask & ~c.satisfied:
            for m in c.members:  # beside `x` on points where every answer was a success, the same cluster
                if _presence(m.expression) and own_answer(m.expression) and polarity(m.expression) == "positive":
                    return [Cluster((m,))]
    return []


def own_answer(expression: str) -> bool:
    """A fact about the agent's own state alone (`self.query_success`, `not self.query_success`,
    `self.query_success is not None`): what its own service call answered. A conversational act that follows
    it in the same turn (a goodbye after the booking went through or after it failed, the user's words between
    them not logged) was not enabled by it; the other party's acts (`self.user.no_more`) are what a
    conversational act answers, and a disjunction that names them keeps the failure as one of its terms
    (`self.user.no_more or not self.query_success`)."""
    node = _parsed(expression)
    if node is None or isinstance(node, ast.BoolOp):
        return False
    paths = [n for n in ast.walk(node) if isinstance(n, ast.Attribute)]
    return bool(paths) and all(isinstance(n.value, ast.Name) and n.value.id == "self" for n in paths)


def spoken_of(clusters: Sequence[Cluster], atoms: Sequence[Cluster], evidence: ActionEvidence, kept: set[int]
              ) -> list[Cluster]:
    """A dialog act's assumed rules, when it speaks of what the user gave (at most of its calls the fact about
    its own argument held: `informed_slot[slot]` at a CONFIRM, not at an OFFER of what a search found): the
    positive facts held at every call about the values it is demonstrated with (`informed_slot['city']`).
    Confirming a city the user never gave is the unguarded state a phase hides: the slots were given long
    before the confirmation, so no trigger names them."""
    n = len(evidence.occurrences)
    given = {ref for c in atoms for ref in _own_lookups(c.representative.expression, evidence.params)
             if n and (c.satisfied & evidence.occurrence_mask).bit_count() * 2 > n}
    values = {value for occ in evidence.occurrences for value in occ.args if isinstance(value, str)}
    return [c for c in assumed(clusters, evidence, kept)
            if any(ref in given and key in values for ref, key in _lookups(c.representative.expression))]


def _own_lookups(expression: str, params: Sequence[str]) -> set[str]:
    """`self.user.informed_slot[slot]` (a parameter as the key, positive) -> {'self.user.informed_slot'}."""
    node = _parsed(expression)
    if isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Name) and node.slice.id in params:
        return {ast.unparse(node.value)}
    return set()


def _lookups(expression: str) -> set[tuple[str, str]]:
    """The literal string keys a condition looks up, with what they are looked up in."""
    node = _parsed(expression)
    return {(ast.unparse(n.value), n.slice.value) for n in ast.walk(node) if isinstance(n, ast.Subscript)
            and isinstance(n.slice, ast.Constant) and isinstance(n.slice.value, str)} if node else set()


def _parsed(expression: str) -> ast.expr | None:
    try:
        return ast.parse(expression, mode="eval").body
    except (SyntaxError, RecursionError, ValueError):
        return None


def unexplained(chosen: Sequence[Cluster], evidence: ActionEvidence) -> bool:
    """Whether some calls were enabled by none of the triggers (each held there, but as a phase)."""
    index = {point: bit for bit, point in enumerate(evidence.points)}
    explained: set[int] = set()
    for c in chosen:
        if enabling_rate(c, evidence, index) >= 1.0:
            return False
        explained |= {k for k, fate in enumerate(enabled_at(c, evidence, index)) if fate}
    return len(explained) < len(evidence.occurrences)


def restated(chosen: Sequence[Cluster], terms: Sequence[Cluster], evidence: ActionEvidence) -> list[Cluster]:
    """Triggers that, at every call they enabled, only re-read news the disjunction's terms state: another term
    about the same state (`query_success is not None` where `not query_success` was made true by a failure),
    or, for a presence test, which says no more than that some answer came, any term. The disjunction
    replaces them."""
    index = {point: bit for bit, point in enumerate(evidence.points)}
    out = []
    for c in chosen:
        read = _leaves(c.representative.expression)
        enabled = {k for k, fate in enumerate(enabled_at(c, evidence, index)) if fate}
        others = [t for t in terms if t.satisfied != c.satisfied and (
            _presence(c.representative.expression) or _overlaps(read, _leaves(t.representative.expression)))]
        news = set().union(*(_made(t, evidence, index) for t in others)) if others else set()
        if others and enabled <= news:
            out.append(c)
    return out


def _leaves(expression: str) -> frozenset[Access]:
    """The state a condition tests, without the objects it passes through (`self.user` in
    `self.user.informed_slot['date']`), so that two conditions about the same user do not overlap."""
    node = _parsed(expression)
    if node is None:
        return frozenset()
    inner = {id(n.value) for n in ast.walk(node) if isinstance(n, ast.Attribute | ast.Subscript)}
    found: set[Access] = set()
    for n in ast.walk(node):
        if id(n) in inner:
            continue
        if isinstance(n, ast.Subscript) and isinstance(n.value, ast.Attribute):
            found.add((n.value.attr, n.slice.value if isinstance(n.slice, ast.Constant) else ANY))
        elif isinstance(n, ast.Attribute):
            found.add((n.attr, ANY))
    return frozenset(found)


def _overlaps(a: frozenset[Access], b: frozenset[Access]) -> bool:
    return any(x == y and (k is ANY or j is ANY or k == j) for x, k in a for y, j in b)


def assumed(clusters: Sequence[Cluster], evidence: ActionEvidence, kept: set[int]) -> list[Cluster]:
    """Positive facts that held at every call and are not already kept."""
    mask = evidence.occurrence_mask
    return [c for c in clusters if c.satisfied not in kept and not mask & ~c.satisfied
            and polarity(c.representative.expression) == "positive"]


def thin_rules(candidates: Sequence[Candidate], evidence: ActionEvidence, n_points: int, tool_call: bool
               ) -> list[Cluster]:
    """An action seen once or twice: the positive facts its calls share that enabled them, the facts about the
    values a dialog act speaks of (`spoken_of`: the slots a confirmation confirms) and the bad news an
    observation wrote just before every one of them (a failure notice after `set_query_status(False)`: `not
    self.query_success`); for a tool call every positive fact they share but those behind a yes
    (`behind_trigger`): the rule the same criterion would keep, on evidence too thin to call it established."""
    mask = evidence.occurrence_mask
    every = informative(cluster([c for c in candidates if mask and not mask & ~c.satisfied]), n_points)
    shared = [c for c in every if polarity(c.representative.expression) == "positive"]
    index = {point: bit for bit, point in enumerate(evidence.points)}
    if tool_call:
        assenting = behind_trigger(shared, evidence)
        return [c for c in shared if not assenting or all(enabled_at(c, evidence, index))
                or not parties(c.representative.expression) <= assenting
                or not confirmed(c.representative.expression, evidence)]
    news = [c for c in every if c not in shared and evidence.writes
            and len(_made(c, evidence, index)) == len(evidence.occurrences)]
    enabled = [c for c in shared if enabling_rate(c, evidence, index) > 0]
    atoms = informative(cluster(candidates), n_points)
    return [*enabled, *news, *spoken_of(every, atoms, evidence, {c.satisfied for c in (*enabled, *news)})]


def disjunction(atoms: Sequence[Cluster], evidence: ActionEvidence, tool_call: bool
                ) -> tuple[Cluster | None, list[Cluster], str, bool]:
    """A greedy cover of the calls by the positive conditions made true just before them, at most MAX_TERMS
    terms, each covering calls no earlier term covers; None unless two or more terms cover every call. Also
    what happened, in words, and whether the search stopped at MAX_DISJUNCTION_ATOMS."""
    index = {point: bit for bit, point in enumerate(evidence.points)}
    atoms = [c for c in atoms if not _presence(c.representative.expression)]  # the value is the news
    positive = [c for c in atoms if polarity(c.representative.expression) == "positive"]
    negative = [c for c in atoms if evidence.writes and c not in positive]  # news only: `_made`
    cut = len(positive) + len(negative) > MAX_DISJUNCTION_ATOMS
    positive, negative = positive[:MAX_DISJUNCTION_ATOMS], negative[:max(0, MAX_DISJUNCTION_ATOMS - len(positive))]
    made = {c.satisfied: _made(c, evidence, index) for c in (*positive, *negative)}
    usable = [*positive, *negative]
    bits = [index.get(occ) for occ in evidence.occurrences]
    uncovered = {k for k, bit in enumerate(bits) if bit is not None}
    terms: list[Cluster] = []
    while uncovered and len(terms) < MAX_TERMS:
        best = max(usable, key=lambda c: (len(made[c.satisfied] & uncovered),
                                            -len(c.representative.expression)), default=None)
        if best is None or not made[best.satisfied] & uncovered:
            break
        terms.append(best)
        uncovered -= made[best.satisfied]  # the calls it enabled (where it merely held, something else did)
    budget = f" (the search looked at the first {MAX_DISJUNCTION_ATOMS} of {len(atoms)} conditions)" if cut else ""
    if uncovered or len(terms) < 2:
        return None, terms, f"no disjunction of at most {MAX_TERMS} triggers covers every call{budget}", cut
    conjuncts = [_term(t, positive, evidence, index, bits) if tool_call else [t] for t in terms]
    expression = " or ".join(_parenthesised(term) for term in conjuncts)
    satisfied = 0
    for term in conjuncts:
        both = (1 << len(evidence.points)) - 1
        for c in term:
            both &= c.satisfied
        satisfied |= both
    mask = evidence.occurrence_mask
    counts = Evidence(mask.bit_count(), (satisfied & mask).bit_count(), len(evidence.points) - mask.bit_count(),
                      (satisfied & ~mask).bit_count())
    if counts.chance() >= CHANCE_ALPHA:
        return None, terms, (f"the disjunction {expression!r} holds about as often where the action was not taken "
                             f"(p = {counts.chance():.2f}): not separated from chance{budget}"), cut
    note = f"a disjunction: each term was made true before the calls it covers{budget}"
    return Cluster((Candidate(expression, terms[0].representative.source, satisfied),)), terms, note, cut


def unread(chosen: Sequence[Cluster]) -> list[Cluster]:
    """The kept rules without a presence test (`x is not None`) beside a test of the same answer's value (`not x`,
    `x`): the value is what the action reports; that some answer came says nothing more, and beside `not x` it
    would refuse before anything was asked, which a failure notice's rule does not."""
    valued = [_leaves(c.representative.expression) for c in chosen if not _presence(c.representative.expression)]
    return [c for c in chosen if not (_presence(c.representative.expression)
                                      and polarity(c.representative.expression) == "positive"
                                      and _leaves(c.representative.expression) in valued)]


def slipped(chosen: Sequence[Cluster], atoms: Sequence[Cluster], evidence: ActionEvidence, share: float
            ) -> tuple[list[Cluster], dict[str, str], dict[str, str]]:
    """The kept rules with each bare presence test (`x is not None`: an answer came) read for its value.

    Beside a kept test of the same answer's value it is dropped (`unread`). Alone, it is the narrowest trigger
    of a failure notice whose calls all followed a failure (`not x` also holds before anything was asked), and
    it may hold at every call only because a human agent once reported the other answer: three "reservation
    failed" notices after a failure and one after a success keep `x is not None`, which allows the notice after
    a success too. When a test of the value (`not x`, `x`) holds at all calls or all but at most `share` of them,
    and at every call where it holds the answer came since the agent's previous turn (the notice reports news),
    it replaces the presence test; the calls it refuses are its exceptions. Also, per replacing rule, why, and
    the presence test it replaced."""
    mask = evidence.occurrence_mask
    n = mask.bit_count()
    index = {point: bit for bit, point in enumerate(evidence.points)}
    out: list[Cluster] = []
    notes: dict[str, str] = {}
    replaced: dict[str, str] = {}
    for c in unread(chosen):
        expression = c.representative.expression
        if not (_presence(expression) and polarity(expression) == "positive"):
            out.append(c)
            continue
        state = _leaves(expression)
        best: tuple[int, Cluster] | None = None
        for v in atoms:
            text = v.representative.expression
            node = _parsed(text)
            if node is None or isinstance(node, ast.BoolOp) or _presence(text) or _leaves(text) != state:
                continue
            holds = (v.satisfied & mask).bit_count()
            if n - holds > share * n or holds <= n - holds or len(_made(v, evidence, index)) < holds:
                continue
            if best is None or holds > best[0]:
                best = (holds, v)
        if best is None:
            out.append(c)
            continue
        holds, v = best
        out.append(v)
        replaced[v.representative.expression] = expression
        slips = (f", so the calls where the agent reported the other answer are its exceptions "
                 f"(options.answer_slips: at most {share:.0%} of the calls)") if holds < n else ""
        notes[v.representative.expression] = (
            f"read for its value: it held at {holds} of {n} calls, each time just after that answer came, and "
            f"replaces {expression!r} (an answer came before every call){slips}")
    return out, notes, replaced


def _made(c: Cluster, evidence: ActionEvidence, index: Mapping[Point, int]) -> set[int]:
    """The calls a condition enabled. A negative condition ("no success") counts only where an observation since
    the agent's previous turn wrote what it reads: the service answered no, which is news; that nothing was
    asked yet is not."""
    fates = enabled_at(c, evidence, index)
    if polarity(c.representative.expression) == "positive":
        return {k for k, fate in enumerate(fates) if fate}
    read = reads(c.representative.expression)
    return {k for k, fate in enumerate(fates)
            if fate and refreshed(read, evidence.occurrences[k],
                                  evidence.previous_turn.get((evidence.occurrences[k].demo,
                                                              evidence.occurrences[k].position), 0),
                                  evidence.writes)}


def _term(trigger: Cluster, positive: Sequence[Cluster], evidence: ActionEvidence, index: Mapping[Point, int],
          bits: Sequence[int | None]) -> list[Cluster]:
    """A tool call's term: the trigger and every positive fact true at every call the trigger enabled."""
    covered = [bits[k] for k, fate in enumerate(enabled_at(trigger, evidence, index)) if fate and bits[k] is not None]
    mask = 0
    for bit in covered:
        mask |= 1 << (bit or 0)
    everything = (1 << len(evidence.points)) - 1
    shared = [c for c in positive if c is not trigger and not mask & ~c.satisfied and c.satisfied != everything]
    return [trigger, *shared]


def _parenthesised(term: Sequence[Cluster]) -> str:
    text = " and ".join(c.representative.expression if len(term) == 1 else f"({c.representative.expression})"
                        for c in term)
    return f"({text})" if len(term) > 1 else text
