"""Amounts a call pays against a balance: "a gift card must have enough balance to cover the price difference".

The balance is a numeric field of an entry a string argument names: an entry of an object field of the read
joined to the call's key (`self.results['get_user_details'][...[order_id]['user_id']]['payment_methods']
[payment_method_id]['balance']`: the owner's payment method). The amount is one the call states or prices:

- a numeric argument (`fee`);
- the total of a numeric field of a list the key's read holds (`sum([y['price'] for y in ...[order_id]['items']])`);
- the prices of the items a list argument names, each priced where it is listed: in a list the key's read holds
  (`max([y['price'] for y in ...[order_id]['items'] if y['item_id'] == x])`), else among the entries of an object
  field of another read's results (`max([R[q]['variants'][x]['price'] for q in R if x in R[q]['variants']])`:
  the variant of any product read); summed, and one list's total less another's (the new items' prices less the
  old ones': the difference the call pays).

`amount <= entry[field]` holds where the entry has the field (`'balance' not in entry or ...`: a credit card has
no balance), and the argument must name an entry of that object (the owner's method). Proposed only where every
demonstrated call meets it and one of them paid from an entry with the field (else nothing shows the balance
read); each candidate is judged by the embedded guard's interpreter on the demonstrated calls' state, so what is
proposed is what the guard and the sandbox evaluate. At most MAX_AMOUNTS an action and read.
"""

from __future__ import annotations

from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

from precond.engine.candidates.tool_conditions import RESULTS
from precond.engine.candidates.tool_facts import Seen, ToolFacts
from precond_client.guard import AGENT_SHAPE
from precond_client.rule_interpreter import Frame, OutsideGrammar, Scope, compile_rule

MAX_AMOUNTS = 8
"""Amount conditions per action and joined read: a few amounts against a balance or two."""
VARIABLES = ("x", "y", "q")
At = Sequence[tuple[Seen, dict[str, Any]]]
"""The demonstrated calls with the result of the read their key names."""


def covered(facts: ToolFacts, at: At, params: Sequence[str], key: str, got: str, prefix: str, name: str,
            other: str) -> list[str]:
    """`prefix and param in owned and (f not in entry or amount <= entry[f])` for each string argument naming an
    entry of an object field of the read joined through `got[name]` (`other`'s results), each numeric field of
    those entries and each amount (module docstring) every demonstrated call meets."""
    if set(VARIABLES) & set(params):
        return []
    owner = f"{RESULTS}[{other!r}][{got}[{name!r}]]"
    amounts = _amounts(facts, at, params, key, got)
    atoms: list[tuple[str, str]] = []
    for param in (p for p in params if p != key and all(isinstance(c.args.get(p), str) for c, _ in at)):
        for field_name in sorted(facts.mappings.get(other, set())):
            owned = f"{owner}[{field_name!r}]"
            entries = [_entry(c, r, other, name, field_name, param) for c, r in at]
            for number in _numeric_fields(entries):
                entry, held = f"{owned}[{param}]", f"{prefix} and {param} in {owned}"
                atoms += [(f"{held} and ({number!r} not in {entry} or {amount} <= {entry}[{number!r}])",
                           f"{held} and {number!r} in {entry}") for amount in amounts]
    return [a for a, read in atoms if _met(a, read, at, params)][:MAX_AMOUNTS]


def _entry(call: Seen, result: dict[str, Any], other: str, name: str, field_name: str, param: str) -> object:
    joined = call.results.get((other, result.get(name)))
    entries = joined.get(field_name) if isinstance(joined, dict) else None
    return entries.get(call.args.get(param)) if isinstance(entries, dict) else None


def _numeric(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _numeric_fields(entries: Sequence[object]) -> list[str]:
    """The fields some entry holds a number in (the balance of the gift cards a call paid from)."""
    return sorted({k for e in entries if isinstance(e, dict) for k, v in e.items() if isinstance(k, str)
                   and _numeric(v)})


def _amounts(facts: ToolFacts, at: At, params: Sequence[str], key: str, got: str) -> list[str]:
    """The amounts a call states or prices (module docstring), as expressions."""
    found = [p for p in params if p != key and all(_numeric(c.args.get(p)) for c, _ in at)]
    first = at[0][1]
    found += [f"sum([y[{f!r}] for y in {got}[{name!r}]])" for name, _, f in _priced_lists(first)
              if _holds(at, lambda c, r, n=name, f=f: all(_numeric(y[f]) for y in r[n]))]
    priced = {p: price for p in params if p != key and (price := _price(facts, at, p, got)) is not None}
    totals = {p: f"sum([{price} for x in {p}])" for p, price in priced.items()}
    found += list(totals.values())
    found += [f"{totals[b]} - {totals[a]}" for a in totals for b in totals if a != b]
    return found


def _priced_lists(result: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(list field, its items' id field, a numeric field of its items) of a read's result."""
    found = []
    for name, items in sorted(result.items()):
        if isinstance(name, str) and isinstance(items, list) and items and all(isinstance(y, dict) for y in items):
            shared = sorted(set.intersection(*(set(y) for y in items)))
            ids = [f for f in shared if isinstance(f, str) and f.endswith("id")]
            found += [(name, ids[0] if ids else "", f) for f in shared if _numeric(items[0][f])]
    return found


def _price(facts: ToolFacts, at: At, param: str, got: str) -> str | None:
    """How each item of a list argument is priced (module docstring), where every demonstrated call's items are."""
    if not all(isinstance(v := c.args.get(param), list) and v and all(isinstance(x, str) for x in v) for c, _ in at):
        return None
    for name, ident, f in _priced_lists(at[0][1]):
        if ident and _holds(at, lambda c, r, n=name, i=ident: all(any(y[i] == x for y in r[n])
                                                                  for x in c.args[param])):
            return f"max([y[{f!r}] for y in {got}[{name!r}] if y[{ident!r}] == x])"
    for tool in sorted(t for t in facts.mappings if t not in facts.writes):
        for name in sorted(facts.mappings[tool]):
            entries = [[v[name] for (t, _), v in c.results.items() if t == tool and isinstance(v, dict)
                        and isinstance(v.get(name), dict)] for c, _ in at]
            for f in _numeric_fields([e for es in entries for entry in es for e in entry.values()]):
                table = f"{RESULTS}[{tool!r}]"
                if all(all(_priced(es, x, f) for x in _items(c, param))
                       for (c, _), es in zip(at, entries, strict=True)):
                    return f"max([{table}[q][{name!r}][x][{f!r}] for q in {table} if x in {table}[q][{name!r}]])"
    return None


def _items(call: Seen, param: str) -> list[object]:
    value = call.args.get(param)
    return value if isinstance(value, list) else []


def _priced(entries: Sequence[dict[str, Any]], item: object, name: str) -> bool:
    """Whether some entry holds `item` as a key, with a number in its field `name` (a variant's price)."""
    return any(isinstance(found := e.get(item), dict) and _numeric(found.get(name))  # type: ignore[call-overload]
               for e in entries)


def _holds(at: At, test: Any) -> bool:
    try:
        return all(test(c, r) for c, r in at)
    except (TypeError, KeyError, AttributeError):
        return False


def _met(atom: str, read: str, at: At, params: Sequence[str]) -> bool:
    """Whether the embedded guard's interpreter finds `atom` true at every demonstrated call, and `read` (the entry
    holds the field) at one of them."""
    scope = Scope(AGENT_SHAPE, tuple(params))
    try:
        rule, reads = compile_rule(atom, scope), compile_rule(read, scope)
    except OutsideGrammar:
        return False
    shown = False
    for call, _ in at:
        state, args = _state(call), [call.args.get(p) for p in params]
        try:
            if not rule(Frame(state, args)):
                return False
            shown = shown or bool(reads(Frame(state, args)))
        except Exception:  # a rule that raises refuses the call: not met
            return False
    return shown


def _state(call: Seen) -> SimpleNamespace:
    """The agent's state at a demonstrated call as a rule reads it: the reads' results by tool and key."""
    results: dict[str, dict[object, object]] = {}
    for (tool, key), value in call.results.items():
        results.setdefault(tool, {})[key] = value
    return SimpleNamespace(results=results, changes={}, errors={}, seen={}, last_ok=True,
                           user=SimpleNamespace(messages=0, last_said=call.said))
