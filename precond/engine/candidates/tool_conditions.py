"""Enumerated conditions over a tool-calling agent's state: the spec `precond convert openai` writes.

There, each tool result is an observation `agent.result(tool, key, ok, value)` that keeps the parsed JSON
result of a read in `self.results[tool][key]`, `key` being the call's identifying argument (a state-changing
tool, named in the spec's module-level `WRITES`, keeps its results in `self.changes`: conditions are about
what the agent read). Generic atoms cannot say
"a successful read of *this* reservation came before the write" or "that reservation is not basic economy",
so this module adds, for an action whose parameter names the key of an earlier tool's results:

- the read: `reservation_id in self.results['get_reservation_details']`;
- fields of that result, with the values the demonstrations show
  (`... and self.results['get_reservation_details'][reservation_id]['cabin'] != 'basic_economy'`), and
  disjunctions of a few of them that together cover every demonstrated call (policies say "if A, or B, or C");
- the call's arguments against the result's field of the same name (`total_baggages >= ...['total_baggages']`,
  `len(passengers) == len(...['passengers'])`); a list argument's items as a set of pairs against the result's
  (`{(x['flight_number'], x['date']) for x in flights} == {... for x in ...['flights']}`), or their ids among the
  result's object of that name (`all(x['payment_id'] in ...['payment_methods'] for x in payment_methods)`);
- with `options.now`, dates of the result against it (`...['created_at'] >= '2024-05-14T15:00:00'`, a day before;
  `all(x['date'] >= '2024-05-15' for x in ...['flights'])`);
- each item of a list argument named in what earlier reads listed (`all(x['flight_number'] in [y['flight_number']
  for y in self.seen['search_direct_flight']] + ... for x in flights)`, the result's list of the same name one
  more source): every search of the conversation, not only the last (`self.seen`, records of list results);
- how many items of a list argument are of a kind read off their ids (`len([x for x in payment_methods if
  'certificate_' in x['payment_id']]) <= 1`);
- the arithmetic a policy states over two integer arguments and a list argument's length, an allowance of k
  (0..3) per item (`nonfree_baggages == max(0, total_baggages - 3 * len(passengers))`: bags beyond the free
  ones are charged, the others not); and an integer argument priced per item of a list, the call's own or one
  of what was read (`any(amount == 100 * len(self.results['get_reservation_details'][x]['passengers']) for x in
  self.results['get_reservation_details'])`: "$100 times the number of passengers" of a reservation read);
  and an argument's few values (`cabin in ('economy',)`), the cells of a table of allowances by category, the k
  of each cell learned from labelled calls (`counterexamples`: free bags by tier and cabin).
  These only separate labelled calls (`arithmetic`, `counterexamples`);
- where a string argument came from, at every demonstrated call (`tool_sources`): the caller's own records,
  only what was offered, the id a look-up found;
- the state a write moves its record out of at every demonstrated call (`tool_transitions`).

The demonstrations are read statically (their literals replayed, never run): which values a field takes and
which a demonstrated call saw only choose what to propose; the sandbox validates every atom like any other.
Everything is bounded: MAX_VALUES values a field, MAX_ATOMS atoms an action.
"""

from __future__ import annotations

import ast
import itertools
import re
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

from precond.engine.candidates.tool_facts import Scalar, Seen, ToolFacts
from precond.engine.candidates.tool_sources import provenance
from precond.engine.candidates.tool_transitions import transitions

RESULTS = "self.results"
SEEN = "self.seen"
MAX_SOURCES = 3
MAX_VALUES = 6
MAX_DISJUNCTS = 3
MAX_DISJUNCTIONS = 24
MIN_COVER = 0.75
MAX_ATOMS = 400
MAX_PAIR_FIELDS = 2
ISO_DATE = re.compile(r"^\d{4}-\d{2}-\d{2}")
def _ordered(values: Iterable[Scalar]) -> bool:
    """Numbers, or ISO dates: fields a threshold is meaningful for."""
    items = list(values)
    numbers = all(isinstance(v, int | float) and not isinstance(v, bool) for v in items)
    return bool(items) and (numbers or all(isinstance(v, str) and ISO_DATE.match(v) for v in items))


@dataclass(frozen=True)
class _Test:
    """A positive condition on a result field and the demonstrated calls it covers (for disjunctions)."""

    text: str
    field: str
    covers: frozenset[int]


class _Builder:
    def __init__(self, facts: ToolFacts, action: str, params: Sequence[str], key: str, tool: str) -> None:
        self.facts, self.params, self.key, self.tool, self.action = facts, params, key, tool, action
        self.table = f"{RESULTS}[{tool!r}]"
        self.has = f"{key} in {self.table}"
        self.got = f"{self.table}[{key}]"
        self.seen = [s.results.get((tool, s.args.get(key))) for s in facts.seen.get(action, [])]

    def read(self) -> list[str]:
        return [self.has, f"{self.key} not in {self.table}"]

    def _at_calls(self, name: str) -> list[object]:
        return [r.get(name) for r in self.seen if isinstance(r, dict)]

    def fields(self) -> tuple[list[str], list[_Test]]:
        atoms: list[str] = []
        tests: list[_Test] = []
        for name, counts in sorted(self.facts.values.get(self.tool, {}).items()):
            common = [v for v, _ in counts.most_common(MAX_VALUES)]
            if len(counts) <= MAX_VALUES and not _counted(counts):
                for value in common:
                    ref = f"{self.got}[{name!r}]"
                    atoms += [f"{self.has} and {ref} == {value!r}", f"{self.has} and {ref} != {value!r}"]
                    tests.append(self._test(f"{ref} == {value!r}", name, _equals(name, value)))
            if _ordered(counts):
                atoms += self._thresholds(name)
        return atoms, tests

    def _thresholds(self, name: str) -> list[str]:
        at_calls = [v for v in self._at_calls(name) if _ordered([v])]  # type: ignore[list-item]
        if not at_calls:
            return []
        ref = f"{self.got}[{name!r}]"
        low, high = min(at_calls), max(at_calls)  # type: ignore[type-var]
        return [f"{self.has} and {ref} >= {low!r}", f"{self.has} and {ref} <= {high!r}"]

    def _test(self, text: str, name: str, holds: Callable[[dict[str, object]], bool]) -> _Test:
        covers = frozenset(i for i, r in enumerate(self.seen) if isinstance(r, dict) and holds(r))
        return _Test(text, name, covers)

    def arguments(self) -> list[str]:
        """The call's own arguments against the same-named field of the result."""
        atoms: list[str] = []
        scalars = self.facts.values.get(self.tool, {})
        for param in self.params:
            if param == self.key:
                continue
            ref = f"{self.got}[{param!r}]"
            if param in scalars:
                ops = ("==", "!=", ">=", "<=") if _ordered(scalars[param]) else ("==", "!=")
                atoms += [f"{self.has} and {param} {op} {ref}" for op in ops]
            if param in self.facts.lists.get(self.tool, set()):
                atoms += [f"{self.has} and len({param}) == len({ref})", f"{self.has} and len({param}) != len({ref})"]
        return atoms

    def collections(self) -> list[str]:
        """A list argument against the result's list of the same name: the same set of (a, b) of its items
        (the flights' (flight_number, date)); and each item's id among the result's object of that name (every
        payment method on the profile)."""
        atoms: list[str] = []
        for param in self.params:
            items = self._argument_items(param)
            if param == self.key or not items:
                continue
            ref = f"{self.got}[{param!r}]"
            shared = sorted(set(items) & set(self.facts.item_fields.get((self.tool, param), {})))[:MAX_PAIR_FIELDS]
            if shared and param in self.facts.lists.get(self.tool, set()):
                pair = "(" + ", ".join(f"x[{k!r}]" for k in shared) + ("," if len(shared) == 1 else "") + ")"
                mine, theirs = f"{{{pair} for x in {param}}}", f"{{{pair} for x in {ref}}}"
                atoms += [f"{self.has} and {mine} == {theirs}", f"{self.has} and {mine} != {theirs}"]
            if param in self.facts.mappings.get(self.tool, set()):
                for name in sorted(k for k in items if k.endswith("id"))[:1]:
                    atoms.append(f"{self.has} and all(x[{name!r}] in {ref} for x in {param})")
        return atoms

    def routes(self) -> list[str]:
        """`listed`, with the result's list of the same name as one more source (a flight change's new
        segments among the searches or the reservation's own flights)."""
        atoms: list[str] = []
        for param in self.params:
            if param == self.key or param not in self.facts.lists.get(self.tool, set()):
                continue
            held = self.facts.item_fields.get((self.tool, param), {})
            ref = f"{self.got}[{param!r}]"
            for name in _item_names(self.facts, self.action, param):
                if name in held and sum(held[name].values()) > 0:
                    own = f"[y[{name!r}] for y in {ref}]"
                    atoms += [f"{self.has} and {text}" for text in listed(self.facts, param, name, own)]
        return atoms

    def endpoints(self) -> list[str]:
        """The route of a list argument's items kept: each item looked up by its `_item_names` field among the
        records earlier reads listed and the result's list of the same name, the airports its segments leave and
        never reach (`{origin} - {destination}`) are those of the result's own list, and those they reach and
        never leave too (degree balance: a one-way trip keeps its origin and destination, a round trip stays a
        closed tour; "ATL to PHL" changed to ATL-DFW-EWR does not). Pairs of item fields whose values overlap
        (airports), at most MAX_PAIR_FIELDS."""
        atoms: list[str] = []
        for param in self.params:
            held = self.facts.item_fields.get((self.tool, param), {})
            if param == self.key or param not in self.facts.lists.get(self.tool, set()) or not held:
                continue
            names = _item_names(self.facts, self.action, param)
            ends = sorted(f for f in held if f not in names)
            pairs = [(a, b) for a in ends for b in ends if a != b and set(held[a]) & set(held[b])]
            for name in (n for n in names if n in held):
                chosen = f"[x[{name!r}] for x in {param}]"
                own = f"{self.got}[{param!r}]"
                for a, b in pairs[:MAX_PAIR_FIELDS]:
                    tools = [t for t in _listing(self.facts, name) if all(
                        self.facts.records[t][f] == self.facts.records[t][""] for f in (a, b))]
                    found = " + ".join([f"{SEEN}[{t!r}]" for t in tools] + [own])
                    new = [f"{{y[{f!r}] for y in {found} if y[{name!r}] in {chosen}}}" for f in (a, b)]
                    old = [f"{{y[{f!r}] for y in {own}}}" for f in (a, b)]
                    atoms.append(f"{self.has} and {new[0]} - {new[1]} == {old[0]} - {old[1]}")
        return atoms

    def _argument_items(self, param: str) -> dict[str, int]:
        """The scalar fields of the dict items of a list argument at the demonstrated calls, by how often."""
        counts: Counter[str] = Counter()
        for seen in self.facts.seen.get(self.action, []):
            value = seen.args.get(param)
            if isinstance(value, list):
                for item in value:
                    if isinstance(item, dict):
                        counts.update(k for k, v in item.items() if isinstance(k, str) and isinstance(v, str | int))
        return dict(counts)

    def moments(self) -> list[str]:
        """With `options.now`: a date-time field within the day before now, and no item of a list dated before
        today (a reservation booked in the last 24 hours; no segment already flown)."""
        now = _moment(self.facts.now)
        if now is None:
            return []
        atoms: list[str] = []
        for name, counts in sorted(self.facts.values.get(self.tool, {}).items()):
            sample = next((v for v in counts if isinstance(v, str) and ISO_DATE.match(v)), None)
            if sample is not None and len(sample) > len("2024-05-15"):
                ref = f"{self.got}[{name!r}]"
                before = (now - timedelta(days=1)).isoformat(timespec="seconds")
                atoms += [f"{self.has} and {ref} >= {before!r}", f"{self.has} and {ref} < {before!r}"]
        for (tool, name), fields in sorted(self.facts.item_fields.items()):
            if tool != self.tool:
                continue
            for key, counts in sorted(fields.items()):
                if _ordered(counts) and all(isinstance(v, str) for v in counts):
                    ref, today = f"{self.got}[{name!r}]", now.date().isoformat()
                    atoms += [f"{self.has} and all(x[{key!r}] >= {today!r} for x in {ref})",
                              f"{self.has} and any(x[{key!r}] < {today!r} for x in {ref})"]
        return atoms

    def disjunctions(self, tests: list[_Test]) -> list[str]:
        """Two or three tests on different fields that together hold at MIN_COVER of the demonstrated calls,
        none of which alone does (policies say "if A, or B, or C"; logs hold a few slips, which evidence-weighted
        validation may tolerate), the most covering first."""
        every = frozenset(i for i, r in enumerate(self.seen) if isinstance(r, dict))
        partial = [t for t in tests if t.covers and t.covers != every]
        if not every or len(partial) < 2:
            return []
        found: list[tuple[int, int, str]] = []
        for size in range(2, MAX_DISJUNCTS + 1):
            for group in itertools.combinations(partial, size):
                covered = frozenset().union(*(t.covers for t in group))
                if (len(covered) >= MIN_COVER * len(every) and len({t.field for t in group}) == size
                        and not _redundant(group)):
                    found.append((-len(covered), size, f"{self.has} and ({' or '.join(t.text for t in group)})"))
        return [text for _, _, text in sorted(found)[:MAX_DISJUNCTIONS]]


def _counted(counts: Counter[Scalar]) -> bool:
    """A field of numbers (a count of bags, an amount): a policy compares it with a threshold or an argument,
    never with one value the logs happen to show (`total_baggages == 3` is a correlate, not a reason)."""
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in counts)


def _equals(name: str, value: Scalar) -> Callable[[dict[str, object]], bool]:
    return lambda result: result.get(name) == value


def _redundant(group: Sequence[_Test]) -> bool:
    """A member whose calls the others already cover adds nothing."""
    return any(t.covers <= frozenset().union(*(o.covers for o in group if o is not t)) for t in group)


def tool_atoms(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """The atoms for one action (a stub of the tool class), at most MAX_ATOMS."""
    atoms: list[str] = []
    for key in params:
        for tool, param in sorted(facts.key_param.items()):
            if param != key or tool == action:
                continue
            builder = _Builder(facts, action, params, key, tool)
            fields, tests = builder.fields()
            atoms += (builder.read() + builder.arguments() + builder.collections() + builder.routes()
                      + builder.endpoints()
                      + builder.moments() + builder.disjunctions(tests) + fields)
    for param in params:
        for name in _item_names(facts, action, param):
            atoms += listed(facts, param, name)
    atoms += kinds(facts, action, params)
    atoms += allowances(facts, action, params)
    atoms += scaled(facts, action, params)
    atoms += keys(facts, action, params)
    atoms += provenance(facts, action, params) + transitions(facts, action, params)
    return list(dict.fromkeys(atoms))[:MAX_ATOMS]


def _item_names(facts: ToolFacts, action: str, param: str) -> list[str]:
    """The fields every dict item of a list argument holds at the demonstrated calls and that name the item rather
    than order it (`flight_number`, not a date or an amount), at most MAX_PAIR_FIELDS, in order: what an item is
    looked up by among what earlier reads listed."""
    values: dict[str, list[Scalar]] = {}
    items = 0
    for seen in facts.seen.get(action, []):
        value = seen.args.get(param)
        for item in value if isinstance(value, list) else []:
            items += 1
            for k, v in item.items() if isinstance(item, dict) else []:
                if isinstance(k, str) and isinstance(v, str | int):
                    values.setdefault(k, []).append(v)
    return sorted(k for k, v in values.items() if len(v) == items and not _ordered(v))[:MAX_PAIR_FIELDS]


def _listing(facts: ToolFacts, name: str) -> list[str]:
    """The tools (at most MAX_SOURCES) every listed record of which holds the field."""
    return sorted(t for t, counts in facts.records.items() if counts[""] and counts[name] == counts[""])[:MAX_SOURCES]


def listed(facts: ToolFacts, param: str, name: str, *more: str) -> list[str]:
    """Each item of a list argument has a `name` that some earlier read listed: `self.seen[tool]` of the (at
    most MAX_SOURCES) tools whose every record holds that field, plus the lists of `more` (the new segments of a
    flight change come from earlier searches: "the route of each segment comes from search results"). Of the
    records the state keeps, the last MAX_SEEN a tool (`precond_client.openai_log.AgentState`)."""
    sources = [f"[y[{name!r}] for y in {SEEN}[{t!r}]]" for t in _listing(facts, name)] + list(more)
    if not sources:
        return []
    return [f"all(x[{name!r}] in {' + '.join(sources)} for x in {param})"]


def separating(atoms: Iterable[str]) -> set[str]:
    """The conditions labelled calls are separated by: all but a field unequal to one value
    (`...['cabin'] != 'basic_economy'`). A policy names what allows a call ("business", "insurance bought"); the
    complement of one value the logs show also admits every value they do not (a cabin, a status to come), and
    a rule made of it refuses calls the policy allows as soon as the other half's logs show them."""
    return {a for a in atoms if not UNEQUAL_VALUE.search(a)}


UNEQUAL_VALUE = re.compile(r"\]\[[^\]]+\] != (?:'[^']*'|-?\d|None|True|False)")
KIND = re.compile(r"^([a-z]+(?:_[a-z]+)*)_\d+$")
MAX_KINDS = 4
KIND_COUNTS = (1, 2, 3)


def kinds(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """How many items of a list argument are of one kind, the kind read off their ids (`certificate_7504069`):
    at most 1, 2 or 3 of each kind the demonstrated calls show ("at most one certificate")."""
    atoms: list[str] = []
    for param in params:
        found: Counter[tuple[str, str]] = Counter()
        for seen in facts.seen.get(action, []):
            value = seen.args.get(param)
            for item in value if isinstance(value, list) else []:
                for name, text in item.items() if isinstance(item, dict) else []:
                    match = KIND.match(text) if isinstance(name, str) and isinstance(text, str) else None
                    if match:
                        found[(name, match.group(1))] += 1
        for name, kind in sorted(k for k, _ in found.most_common(MAX_KINDS)):
            counted = f"len([x for x in {param} if {kind + '_'!r} in x[{name!r}]])"
            atoms += [f"{counted} <= {n}" for n in KIND_COUNTS]
    return atoms


ALLOWANCES = (3, 2, 1, 0)
"""Allowances per item, the largest first: with no call to allow, of the limits that refuse the same calls
labelled 'refuse' the first (the most generous allowance) is chosen."""
ARITHMETIC = re.compile(r"^\w+ == max\(0, \w+ - (\d) \* len\(\w+\)\)$")


def allowances(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """`b == max(0, a - k * len(items))` for two arguments that are integers at every seen call of the action
    and a list argument: the charged part `b` of a count `a` is what exceeds an allowance of k per item ("each
    passenger has k free bags; each extra one is paid"). Only actions whose calls show such arguments get them, and
    only lists of what the call brings, not of references to what was read (a flight some search listed, a payment
    method among the profile's): an allowance is per passenger, not per segment or payment."""
    calls = facts.seen.get(action, [])
    if not calls:
        return []
    integers = [p for p in params if all(_integer(c.args.get(p)) for c in calls)]
    lists = _own_lists(facts, action, params)
    return [f"{b} == max(0, {a} - {k} * len({n}))"
            for k in ALLOWANCES for a, b in itertools.permutations(integers, 2) for n in lists]


MAX_KEYS = 4
"""Categories an allowance's table is looked up by (`keys`), at most: a table keyed by one or two of them."""
MAX_CELLS = 9
"""Cells of a table (the values of its one or two categories), at most."""
ARGUMENT_KEY = re.compile(r"^\w+ in \('[^'\\]*',\)$")
"""An argument's category (`keys`): a one-value tuple, which no other condition of the enumerator's writes and a
code model hardly does, so the ranking can leave it out (`arithmetic`) without leaving out anything else."""
READ_KEY = re.compile(r"^(\w+ in self\.results\['\w+'\]) and (self\.results\['\w+'\]\[\w+\]\['\w+'\]) == ('[^'\\]*')$")


def keys(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """`cabin in ('economy',)`: an argument that takes a few strings (2 to MAX_VALUES) at the seen calls of an action
    with allowances, each value a cell of a table of allowances ("free bags by tier and cabin"; the tier is a field
    of a read the call names, `_Builder.fields` proposes it). Not an argument naming a read's result (an id is
    no category). Like the arithmetic it keys, chosen only to separate labelled calls (`arithmetic`)."""
    calls = facts.seen.get(action, [])
    if not allowances(facts, action, params):
        return []
    ids = set(facts.key_param.values())
    atoms: list[str] = []
    for param in params:
        values = [c.args.get(param) for c in calls]
        if param in ids or not all(isinstance(v, str) for v in values) or _ordered(values):  # type: ignore[arg-type]
            continue
        found = sorted({v for v in values if isinstance(v, str)})
        if 2 <= len(found) <= MAX_VALUES:
            atoms += [f"{param} in {(v,)!r}" for v in found if ARGUMENT_KEY.match(f"{param} in {(v,)!r}")]
    return atoms


def key(atom: str) -> tuple[str | None, str, str] | None:
    """A cell of a category (`keys`, or a read's field `_Builder.fields` proposes): the read it needs (None for an
    argument), the category, the value; None for any other condition."""
    if ARGUMENT_KEY.match(atom):
        name, _, value = atom.partition(" in ")
        return None, name, str(ast.literal_eval(value)[0])
    match = READ_KEY.match(atom)
    return (match.group(1), match.group(2), str(ast.literal_eval(match.group(3)))) if match else None


def _own_lists(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """The list arguments of what the call brings (passengers), not of references to what was read (a flight some
    search listed, a payment method among the profile's): what an allowance or a price counts per item."""
    calls = facts.seen.get(action, [])
    referred = set().union(*facts.mappings.values()) if facts.mappings else set()
    return [p for p in params if calls and all(isinstance(c.args.get(p), list) for c in calls) and p not in referred
            and not any(_listing(facts, name) for name in _item_names(facts, action, p))]


def _own_records(facts: ToolFacts, tool: str) -> list[str]:
    """A read's list fields of records that refer to nothing else read (a reservation's passengers, not its
    flights, which searches listed, nor its payments, which name the profile's payment methods)."""
    own = []
    for name in sorted(facts.lists.get(tool, set())):
        fields = facts.item_fields.get((tool, name), {})
        names = [f for f, values in fields.items() if not _ordered(values)]
        if fields and not any(_listing(facts, f) or set(fields[f]) & facts.entries for f in names):
            own.append(name)
    return own


def allowance(atom: str) -> int:
    """The k of an allowance (`allowances`), -1 for any other condition."""
    match = ARITHMETIC.match(atom)
    return int(match.group(1)) if match else -1


def allowance_form(atom: str) -> str:
    """An allowance with `{}` for its k: the allowances of one form differ only by k."""
    match = ARITHMETIC.match(atom)
    return f"{atom[:match.start(1)]}{{}}{atom[match.end(1):]}" if match else atom


def _integer(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


SCALED = re.compile(r"^(?:\w+ in self\.results\[[^\]]+\] and |any\()?\w+ == \d+ \* len\(")


@dataclass(frozen=True)
class _Items:
    """Where the items a price counts are: the list argument `name` (no `tool`), or the list field `name` of the
    result of the read `tool` that the call's argument `key` names, or of any result of it (no `key`)."""

    text: str
    """The condition, with `{0}` for the argument and `{1}` for the price."""
    name: str
    tool: str | None = None
    key: str | None = None

    def at(self, call: Seen) -> list[object]:
        if self.tool is None:
            return [call.args.get(self.name)]
        if self.key is not None:
            return [_field(call.results.get((self.tool, call.args.get(self.key))), self.name)]
        return [_field(value, self.name) for (tool, _), value in call.results.items() if tool == self.tool]


def scaled(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """`a == k * len(items)` for an argument `a` that is an integer at every seen call of the action: an amount
    priced per item ("$100 times the number of passengers"). The items are records of their own (`_own_lists`,
    `_own_records`): a list argument of the call, or a list field of a read's result, the one the call names by
    its key (`reservation_id in ... and amount == 100 * len(...[reservation_id]['passengers'])`) or, where no
    parameter of the action keys that read, any result of it (`any(amount == 100 * len(...[x]['passengers']) for
    x in ...)`: a compensation for one of the reservations read). Not an argument that a read's result counts too
    (`total_baggages`): that one is compared with what it was, or shares out as an allowance, and its equality
    with a multiple is a logged count scaled (a correlate, as `total_baggages == 3` is). The prices k are what
    the seen calls show, `a // len(items)` wherever that divides, at most MAX_VALUES an argument and a list, the
    most common first: a price is read off the calls, never assumed."""
    calls = facts.seen.get(action, [])
    counts = {name for values in facts.values.values() for name, held in values.items() if _counted(held)}
    integers = [p for p in params if calls and p not in counts and all(_integer(c.args.get(p)) for c in calls)]
    keyed = {tool: param for tool, param in facts.key_param.items() if param in params}
    sources = [_Items(f"{{0}} == {{1}} * len({name})", name) for name in _own_lists(facts, action, params)]
    for tool in sorted(facts.lists):
        table = f"{RESULTS}[{tool!r}]"
        for name in _own_records(facts, tool):
            key = keyed.get(tool)
            sources.append(_Items(f"{key} in {table} and {{0}} == {{1}} * len({table}[{key}][{name!r}])"
                                  if key else f"any({{0}} == {{1}} * len({table}[x][{name!r}]) for x in {table})",
                                  name, tool, key))
    atoms: list[str] = []
    for argument in integers:
        for items in sources:
            prices: Counter[int] = Counter()
            for call in calls:
                prices.update(_prices(call.args.get(argument), items.at(call)))
            ordered = sorted(prices.items(), key=lambda price: (-price[1], price[0]))
            atoms += [items.text.format(argument, k) for k, _ in ordered[:MAX_VALUES]]
    return atoms


def _prices(amount: object, lists: Sequence[object]) -> set[int]:
    """The prices per item an amount is a whole multiple of, one a non-empty list."""
    if isinstance(amount, bool) or not isinstance(amount, int) or amount <= 0:
        return set()
    return {amount // len(items) for items in lists if isinstance(items, list) and items and not amount % len(items)}


def _field(value: object, name: str) -> object:
    return value.get(name) if isinstance(value, dict) else None


def arithmetic(atom: str) -> bool:
    """An allowance (`allowances`), an amount priced per item (`scaled`) or an argument's category an allowance's
    table is keyed by (`keys`): chosen only to separate calls labelled 'refuse', never kept from demonstrations
    alone (a count that happens to fit the logs is a correlate, and so is the one cabin the logs show)."""
    return bool(ARITHMETIC.match(atom) or SCALED.match(atom) or ARGUMENT_KEY.match(atom))


def _moment(text: str | None) -> datetime | None:
    try:
        return datetime.fromisoformat(text) if text else None
    except ValueError:
        return None
