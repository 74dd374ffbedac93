"""Relations between a tool call and what came before it: the conditions a policy states about *this* key.

`tool_conditions` proposes what one read says about the call's key (read before, a field's value, the
argument against the field of the same name). A policy also relates the call to other calls and other reads:

- what earlier writes' results on the same key show of a field the read holds at one value at every call
  (`shown_by_writes`: no earlier result of a write shows the order other than 'pending');
- an earlier write on the same key (`order_id not in self.changes['modify_pending_order_items']`: "can only be
  modified once"; `order_id in self.changes['cancel_pending_order']`: a refund after the cancellation of *that*
  order), for each state-changing tool with a parameter of the same name, both ways;
- an argument among the few values the demonstrated calls give it (`reason in ('no longer needed', 'ordered by
  mistake')`), for a string argument with 2 to MAX_VALUES values that names no read's key;
- an argument compared with an ordered field of the read its key names (`amount <= ...['total']`, `date <= ...
  ['departure']`), with the comparisons every demonstrated call keeps;
- a list argument contained in a list the read holds (`all(x in [y['item_id'] for y in ...['items']] for x in
  item_ids)`: the items of that order), where every demonstrated call's items are there;
- a join of two reads: a field of the read the call names is a key of another read, or an id a lookup found
  (`...[order_id]['user_id'] in [self.results['find_user_id_by_email'][k] for k in ...]`: the order's customer is
  the authenticated one), and an argument in an entry of that other read (`payment_method_id in
  self.results['get_user_details'][...[order_id]['user_id']]['payment_methods']`: the owner's payment method),
  and an amount the call states or prices covered by a numeric field of that entry (`tool_amounts.covered`: the
  price difference within the gift card's balance);
- two list arguments whose items are keys of an object field of one read's results, as many on both sides in
  each result (`variants`: each new item a variant of the product of the item it replaces), at most MAX_VALUES;
- a string argument among (or, where every call shows it and both are ids, not among) a field of a list the
  read holds (`payment_method_id in [y['payment_method_id'] for y in ...['payment_history']]`: the original
  payment method), one per list field and item field (`_list_fields`: two an item);
- a string argument's kind read off its id (`'gift_card_' in payment_method_id`), where the demonstrated calls
  show 2 to MAX_KINDS kinds;
- what the user said last before the call, where the demonstrated calls share it (`self.user.last_said ==
  'yes'`: an explicit confirmation).

Each is proposed only where the demonstrated calls show it holding (the values seen type it: an id is no category, a
date is compared with a date), except the earlier writes, which the demonstrations cannot show refused and the
labels decide (and what their results show), and an argument among a listed field and the kinds, which need only
hold at some call: the labels decide those too. At most MAX_RELATIONS an action: a handful per key, read and
argument, so a request's search stays within its work budget (`engine.decisive`). Every condition is one the
embedded guard runs (`runnable`): one it cannot is never proposed.
"""

from __future__ import annotations

import itertools
import operator
import re
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from precond.engine.candidates.tool_amounts import covered
from precond.engine.candidates.tool_conditions import KIND, MAX_KINDS, MAX_VALUES, RESULTS, arithmetic
from precond.engine.candidates.tool_facts import Seen, ToolFacts
from precond_client.guard import AGENT_SHAPE
from precond_client.rule_interpreter import OutsideGrammar, Scope, compile_rule

MAX_RELATIONS = 48
"""Relation conditions per action, at most: 6 writes x 2 ways, a few categories, joins, containments and kinds."""
CHANGES = "self.changes"
SAID = "self.user.last_said"


EARLIER_WRITE = re.compile(r"^\w+ (?:not )?in self\.changes\['\w+'\]$")
SHOWN = re.compile(r"^all\(self\.changes\[w\]")


def labels_only(atom: str) -> bool:
    """An earlier write on the same key (`earlier_writes`), what earlier writes' results show (`shown_by_writes`),
    or the arithmetic of a tool spec
    (`tool_conditions.arithmetic`): chosen only to separate labelled calls, never kept from demonstrations alone
    (that a flight change came before every baggage change in the logs is their order, not a requirement)."""
    return bool(EARLIER_WRITE.match(atom) or SHOWN.match(atom)) or arithmetic(atom)


def relations(facts: ToolFacts, action: str, params: Sequence[str]) -> list[str]:
    """The relation conditions of one action (module docstring), each runnable by the embedded guard."""
    calls = facts.demonstrated_calls(action)
    atoms = [*earlier_writes(facts, params, action), *categories(facts, calls, params), *confirmation(calls),
             *variants(facts, calls, params), *scalar_kinds(calls, params)]
    for key in params:
        for tool, param in sorted(facts.key_param.items()):
            if param == key and tool != action:
                atoms += _about_read(facts, calls, params, key, tool) + shown_by_writes(facts, calls, key, tool)
    return runnable(list(dict.fromkeys(atoms)), params)[:MAX_RELATIONS]


def runnable(atoms: Iterable[str], params: Sequence[str]) -> list[str]:
    """The conditions the embedded guard (`precond_client.rule_interpreter`) compiles; the others are dropped."""
    scope = Scope(AGENT_SHAPE, tuple(params))
    kept = []
    for atom in atoms:
        try:
            compile_rule(atom, scope)
        except OutsideGrammar:
            continue
        kept.append(atom)
    return kept


def earlier_writes(facts: ToolFacts, params: Sequence[str], action: str = "") -> list[str]:
    """`key in / not in self.changes[W]` for each write W with a parameter named as one of the call's keys; of the
    action itself only `not in` ("once per key"): requiring its own earlier success would refuse the first call
    on every key, so no policy can state it, however well it fits calls labelled 'refuse' (each run's first)."""
    keys = set(facts.key_param.values())
    atoms = []
    for key in (p for p in params if p in keys):
        for write in sorted(w for w in facts.writes if key in facts.params.get(w, ())):
            atoms += [f"{key} not in {CHANGES}[{write!r}]"] + ([f"{key} in {CHANGES}[{write!r}]"] * (write != action))
    return atoms


def categories(facts: ToolFacts, calls: Sequence[Seen], params: Sequence[str]) -> list[str]:
    """`param in (values...)` for a string argument that names nothing (no read's key, no `*_id`, no `card_7`-like
    values) and takes 2..MAX_VALUES values."""
    keys = set(facts.key_param.values())
    atoms = []
    for param in params:
        values = [c.args.get(param) for c in calls]
        found = sorted({v for v in values if isinstance(v, str)})
        named = param.endswith(("id", "ids")) or any(KIND.match(v) for v in found)  # an id is no category
        if param not in keys and not named and values and all(isinstance(v, str) for v in values) \
                and 2 <= len(found) <= MAX_VALUES:
            atoms.append(f"{param} in {tuple(found)!r}")
    return atoms


def confirmation(calls: Sequence[Seen]) -> list[str]:
    """`self.user.last_said == v` where every demonstrated call came right after the user said v."""
    said = {c.said for c in calls}
    value = next(iter(said)) if len(said) == 1 else None
    return [f"{SAID} == {value!r}"] if isinstance(value, str) and len(calls) >= 2 and len(value) <= 40 else []


def _about_read(facts: ToolFacts, calls: Sequence[Seen], params: Sequence[str], key: str, tool: str) -> list[str]:
    table = f"{RESULTS}[{tool!r}]"
    has, got = f"{key} in {table}", f"{table}[{key}]"
    read = [c.results.get((tool, c.args.get(key))) for c in calls]
    at = [(c, r) for c, r in zip(calls, read, strict=True) if isinstance(r, dict)]
    if not at or len(at) < len(calls):
        return []
    atoms = [f"{has} and {a}" for a in _compared(at, params, key, got) + _contained(at, params, key, got)
             + _recorded(at, params, key, got)]
    for name, other, render in _joins(facts, at, tool):
        joined = render.format(f"{got}[{name!r}]")
        atoms.append(f"{has} and {joined}")
        atoms += [f"{has} and {joined} and {a}" for a in _owned(facts, at, params, key, name, other, got)]
        atoms += covered(facts, at, params, key, got, f"{has} and {joined}", name, other)
    return atoms


At = Sequence[tuple[Seen, dict[str, Any]]]
"""The demonstrated calls with the result of the read their key names."""


def _holds(at: At, test: Callable[..., Any], *extra: Any) -> bool:
    """Whether `test(call, result, *extra)` holds at every demonstrated call (one that raises does not)."""
    try:
        return all(test(c, r, *extra) for c, r in at)
    except (TypeError, KeyError, AttributeError):
        return False


def _ordered(value: object) -> bool:
    return isinstance(value, int | float | str) and not isinstance(value, bool)


def _compared(at: At, params: Sequence[str], key: str, got: str) -> list[str]:
    """An ordered argument against an ordered field of another name, of the same type, both ways it holds."""
    atoms = []
    for param in (p for p in params if p != key):
        for name in sorted(k for k in at[0][1] if isinstance(k, str) and k != param):
            pairs: list[tuple[Any, Any]] = [(c.args.get(param), r.get(name)) for c, r in at]
            if not all(_comparable(a, b) for a, b in pairs):
                continue
            atoms += [f"{param} {op} {got}[{name!r}]" for op, test in (("<=", operator.le), (">=", operator.ge))
                      if all(test(a, b) for a, b in pairs)]
    return atoms


def _comparable(a: Any, b: Any) -> bool:
    """Two numbers, or two dates (strings that start with a year), of one type."""
    return _ordered(a) and _ordered(b) and type(a) is type(b) and (
        not isinstance(a, str) or (a[:4].isdigit() and b[:4].isdigit()))


def _contained(at: At, params: Sequence[str], key: str, got: str) -> list[str]:
    """A list argument of scalars within a list field's items' field, at every demonstrated call."""
    atoms = []
    for param in _scalar_lists(at, params, key):
        for name, inner in _list_fields(at[0][1]):
            if _holds(at, _within, param, name, inner):
                atoms.append(f"all(x in [y[{inner!r}] for y in {got}[{name!r}]] for x in {param})")
    return atoms


def _scalar_lists(at: At, params: Sequence[str], key: str) -> list[str]:
    """The arguments but the key that are lists of strings or numbers at every demonstrated call (item ids)."""
    def scalars(value: Any) -> bool:
        return isinstance(value, list) and all(isinstance(x, str | int) for x in value)
    return [p for p in params if p != key and all(scalars(c.args.get(p)) for c, _ in at)]


def _within(call: Seen, result: dict[str, Any], param: str, name: str, inner: str) -> bool:
    return all(x in [y[inner] for y in result[name]] for x in call.args[param])  # type: ignore[attr-defined]


def _keyed(call: Seen, result: dict[str, Any], other: str, name: str) -> bool:
    return (other, result[name]) in call.results


def _found(call: Seen, result: dict[str, Any], other: str, name: str) -> bool:
    return result[name] in [v for (tool, _), v in call.results.items() if tool == other]


def _list_fields(result: dict[str, object]) -> list[tuple[str, str]]:
    """(list field, a string field every item holds) of a result, the fields named as ids first."""
    found = []
    for name, items in sorted(result.items()):
        if isinstance(name, str) and isinstance(items, list) and items and all(isinstance(y, dict) for y in items):
            shared = set.intersection(*(set(y) for y in items))
            found += [(name, f) for f in sorted(shared, key=lambda f: (not f.endswith("id"), f))
                      if isinstance(f, str) and all(isinstance(y[f], str) for y in items)][:2]
    return found


def _joins(facts: ToolFacts, at: At, tool: str) -> list[tuple[str, str, str]]:
    """(field, other read, a template saying that the field's value `{}` is among that read's keys or the ids it
    found), for each string field of the read and other read where every demonstrated call shows it so."""
    joins: list[tuple[str, str, str]] = []
    others = sorted({t for c, _ in at for t, _ in c.results if t != tool})
    for name in sorted(k for k, v in at[0][1].items() if isinstance(k, str) and isinstance(v, str)):
        for other in others:
            table = f"{RESULTS}[{other!r}]"
            if _holds(at, _keyed, other, name):
                joins.append((name, other, f"{{}} in {table}"))
            if _holds(at, _found, other, name):
                joins.append((name, other, f"{{}} in [{table}[k] for k in {table}]"))
    return joins[:MAX_VALUES]


def _owned(facts: ToolFacts, at: At, params: Sequence[str], key: str, name: str, other: str, got: str) -> list[str]:
    """A string argument among the entries of an object field of the joined read (the owner's payment methods)."""
    atoms = []
    entry = f"{RESULTS}[{other!r}][{got}[{name!r}]]"
    for param in (p for p in params if p != key):
        for field_name in sorted(facts.mappings.get(other, set())):
            def owned(c: Seen, r: dict[str, Any], p: str = param, f: str = field_name) -> bool:
                joined = c.results.get((other, r[name]))
                return isinstance(c.args.get(p), str) and isinstance(joined, dict) and c.args[p] in joined[f]
            if _holds(at, owned):
                atoms.append(f"{param} in {entry}[{field_name!r}]")
    return atoms


def _scalar_strings(at: At | Sequence[Seen], params: Sequence[str]) -> list[str]:
    """The arguments that are strings at every demonstrated call."""
    calls = [c if isinstance(c, Seen) else c[0] for c in at]
    return [p for p in params if calls and all(isinstance(c.args.get(p), str) for c in calls)]


def _recorded(at: At, params: Sequence[str], key: str, got: str) -> list[str]:
    """A string argument among, or not among, a field of a list field's items of the read (`payment_method_id in
    [y['payment_method_id'] for y in ...['payment_history']]`: "the original payment method", or "a method other
    than the original one"): `in` where some demonstrated call shows it, `not in` where every one does and the
    argument and those items are ids read as such (`credit_card_...`, `KIND`), so that the two can be equal."""
    atoms = []
    for param in (p for p in _scalar_strings(at, params) if p != key):
        for name, inner in _list_fields(at[0][1]):
            listed = f"[y[{inner!r}] for y in {got}[{name!r}]]"
            held = [_holds([(c, r)], _within_scalar, param, name, inner) for c, r in at]
            if any(held):
                atoms.append(f"{param} in {listed}")
            elif _holds(at, _same_kind, param, name, inner):
                atoms.append(f"{param} not in {listed}")
    return atoms


def _within_scalar(call: Seen, result: dict[str, Any], param: str, name: str, inner: str) -> bool:
    return call.args[param] in [y[inner] for y in result[name]]


def _same_kind(call: Seen, result: dict[str, Any], param: str, name: str, inner: str) -> bool:
    """The argument is not among the items' field, and it and they are ids (`KIND`)."""
    return call.args[param] not in [y[inner] for y in result[name]] and all(
        KIND.match(str(v)) for v in [call.args[param], *(y[inner] for y in result[name])])


def scalar_kinds(calls: Sequence[Seen], params: Sequence[str]) -> list[str]:
    """`'gift_card_' in payment_method_id`: a string argument's kind read off its id (`KIND`), for an argument
    whose demonstrated values are of 2 to MAX_KINDS kinds (one kind says nothing): "or an existing gift card"."""
    atoms = []
    for param in _scalar_strings(calls, params):
        found = [KIND.match(str(c.args[param])) for c in calls]
        kinds = sorted({m.group(1) for m in found if m})
        if all(found) and 2 <= len(kinds) <= MAX_KINDS:
            atoms += [f"{kind + '_'!r} in {param}" for kind in kinds]
    return atoms


def variants(facts: ToolFacts, calls: Sequence[Seen], params: Sequence[str]) -> list[str]:
    """Two list arguments (item ids and the new ids they become) whose items are keys of an object field of the
    results of one read (the variants of a product read), both sides as many in each result: each new item is
    a variant of the same product as the item it replaces ("no change of product type"). One condition per pair
    of list arguments and (read, object field) where every demonstrated call shows it; at most MAX_VALUES."""
    lists = [p for p in params if calls and all(_scalar_list(c.args.get(p)) for c in calls)]
    atoms = []
    for a, b in itertools.combinations(lists, 2):
        for tool in sorted(t for t in facts.mappings if t not in facts.writes):
            for name in sorted(facts.mappings[tool]):
                if calls and all(_same_entries(c, a, b, tool, name) for c in calls):
                    table, keyed = f"{RESULTS}[{tool!r}]", f"{RESULTS}[{tool!r}][p][{name!r}]"
                    atoms.append(f"all(any(x in {keyed} for p in {table}) for x in {a} + {b}) and "
                                 f"all(len([x for x in {a} if x in {keyed}]) == len([x for x in {b} if x in {keyed}])"
                                 f" for p in {table})")
    return atoms[:MAX_VALUES]


def _scalar_list(value: object) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(x, str | int) for x in value)


def _same_entries(call: Seen, a: str, b: str, tool: str, name: str) -> bool:
    """Whether every item of `a` and `b` is a key of `name` in some result of `tool`, both as many in each."""
    entries = [v[name] for (t, _), v in call.results.items() if t == tool and isinstance(v, dict)
               and isinstance(v.get(name), dict)]
    first, second = (v if isinstance(v := call.args.get(p), list) else [] for p in (a, b))
    return all(any(x in e for e in entries) for x in first + second) and all(
        sum(x in e for x in first) == sum(x in e for x in second) for e in entries)


def shown_by_writes(facts: ToolFacts, calls: Sequence[Seen], key: str, tool: str) -> list[str]:
    """`all(self.changes[w][order_id]['status'] == 'pending' for w in (...) if order_id in self.changes[w])`: a
    write's result shows the record too (an order whose items were modified is 'pending (items modified)', a
    cancelled one 'cancelled'), so a field the read's result holds at one value at every demonstrated call
    (at most MAX_VALUES values in all) holds it in every earlier result of a write on the same key as well.
    Each write with a parameter named as the key; one condition per such field. Chosen only to separate labelled
    calls (`labels_only`): the demonstrations show writes' results no more refused than the writes."""
    writes = tuple(sorted(w for w in facts.writes if key in facts.params.get(w, ())))
    read = [c.results.get((tool, c.args.get(key))) for c in calls]
    if not writes or not read or not all(isinstance(r, dict) for r in read):
        return []
    atoms = []
    for name, counts in sorted(facts.values.get(tool, {}).items()):
        values = {r.get(name) for r in read if isinstance(r, dict)}
        value = next(iter(values)) if len(values) == 1 else None
        if isinstance(value, str) and len(counts) <= MAX_VALUES:
            atoms.append(f"all({CHANGES}[w][{key}][{name!r}] == {value!r} for w in {writes!r} if {key} in "
                         f"{CHANGES}[w])")
    return atoms
