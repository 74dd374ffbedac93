"""Allowances a tool's policy states, learned from labelled calls: one k for every call, or a k by category.

`counterexamples.separate` tightens an action's rule with them last (`tool_conditions.allowances`: "k free bags
a passenger"; `tool_conditions.keys`: the categories a table of them is looked up by): `best_allowance` picks the one k
that refuses the most of the calls labelled 'refuse' the other conditions leave allowed; `table` a k per cell
of one or two categories, only where one k cannot separate those calls.
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from precond.engine.candidates.tool_conditions import ALLOWANCES, MAX_CELLS, MAX_KEYS, allowance, allowance_form, key


def held_terms(terms: Sequence[tuple[str, ...]], values: Mapping[str, int], every: int) -> int:
    """Where a disjunction of terms (conjunctions of conditions) holds, from where each condition holds."""
    held = 0
    for term in terms:
        value = every
        for e in term:
            value &= values.get(e, 0)
        held |= value
    return held


def best_allowance(truth: Mapping[str, int], positive: int, negative: int, remaining: int) -> list[str]:
    """The largest allowance (the most generous, `tool_conditions.allowance`) that holds at every call to allow (or,
    with none, at some call labelled 'refuse': one no call meets says no more than `False`) and refuses the most
    of the calls labelled 'refuse' that the other conditions leave allowed (`remaining`); none if none does.
    Chosen after the others, so it never replaces a condition that already separates."""
    best, refused = None, 0
    for e, t in sorted(truth.items(), key=lambda item: -allowance(item[0])):
        meets = not positive & ~t if positive else bool(t & negative)
        if meets and (remaining & ~t).bit_count() > refused:
            best, refused = e, (remaining & ~t).bit_count()
    return [best] if best else []


Category = tuple[str | None, str]
"""A table's key (`tool_conditions.key`): the read it needs (None for an argument of the call), the reference."""


@dataclass(frozen=True)
class Table:
    """An allowance looked up by one or two categories: per k other than the fallback's, the cells that get it
    (each cell the conditions that place a call in it, `tool_conditions.key`); any other value the fallback."""

    reads: tuple[str, ...]
    groups: tuple[tuple[tuple[tuple[str, ...], ...], str], ...]
    """(the cells, the allowance they get), the most generous first."""
    fallback: str
    text: str
    reason: str

    def held(self, values: Mapping[str, int], every: int) -> int:
        """Where the table holds, from where each condition it is made of holds."""
        inside = held = 0
        for cells, allowed in self.groups:
            member = 0
            for cell in cells:
                member |= held_terms([cell], values, every)
            inside |= member
            held |= member & values.get(allowed, 0)
        held |= every & ~inside & values.get(self.fallback, 0)
        return held_terms([self.reads], values, every) & held


def table(truth: Mapping[str, int], positive: int, remaining: int, every: int, flat: Sequence[str]
           ) -> Table | None:
    """The allowance looked up by one or two categories (an argument of the call, a field of a read it names:
    "free bags by tier and cabin") that refuses more of the calls labelled 'refuse' the other conditions leave
    allowed (`remaining`) than the flat allowance (`flat`, `best_allowance`) does; None where none does. Each cell a
    call to allow or a labelled call shows gets, of the ks consistent with every call to allow in it, the one
    refusing the most of `remaining` there (then the fallback's, then the most generous); a cell no call shows,
    and a value none of the reads or calls showed, gets the fallback: the flat allowance's k, else the smallest
    k of the table (no unseen category gets more than every seen one). At most MAX_KEYS categories (the fewest
    values first), MAX_CELLS cells a table; the fewer categories, then the shorter text, on a tie."""
    forms: dict[str, dict[int, str]] = {}
    categories: dict[Category, dict[str, str]] = {}
    for e in truth:
        if allowance(e) >= 0:
            forms.setdefault(allowance_form(e), {})[allowance(e)] = e
        found = key(e)
        if found and (found[0] is None or found[0] in truth):
            categories.setdefault(found[:2], {})[found[2]] = e
    usable = sorted((c for c, values in categories.items() if len(values) >= 2),
                    key=lambda c: (len(categories[c]), c[1]))[:MAX_KEYS]
    refused = (remaining & ~truth[flat[0]]).bit_count() if flat else 0
    best: tuple[tuple[int, int, int], Table] | None = None
    for form, by_k in sorted(forms.items()):
        fixed = allowance(flat[0]) if flat and allowance_form(flat[0]) == form else None
        for chosen in [*itertools.combinations(usable, 1), *itertools.combinations(usable, 2)]:
            cells = list(itertools.product(*(sorted(categories[c].items()) for c in chosen)))
            table = filled(truth, positive, remaining, every, by_k, fixed, chosen, cells) \
                if len(cells) <= MAX_CELLS else None
            if table is None:
                continue
            held = table.held(truth, every)
            score = (-(remaining & ~held).bit_count(), len(chosen), len(table.text))
            if not positive & ~held and -score[0] > refused and (best is None or score < best[0]):
                best = (score, table)
    return best[1] if best else None


def filled(truth: Mapping[str, int], positive: int, remaining: int, every: int, by_k: Mapping[int, str],
            fixed: int | None, chosen: Sequence[Category], cells: Sequence[tuple[tuple[str, str], ...]]
            ) -> Table | None:
    """The table of one allowance's form over the categories `chosen` (`table`); None where a cell's calls to
    allow fit no one k, or every cell gets the fallback (the flat allowance)."""
    ks: dict[tuple[tuple[str, str], ...], int] = {}
    for cell in cells:
        inside = held_terms([tuple(atom for _, atom in cell)], truth, every)
        fits = [k for k in ALLOWANCES if k in by_k and not positive & inside & ~truth[by_k[k]]]
        if not fits:
            return None
        if inside:
            ks[cell] = max(fits, key=lambda k: ((remaining & inside & ~truth[by_k[k]]).bit_count(), k == fixed, k))
    fallback = fixed if fixed is not None else min(ks.values(), default=-1)
    if fallback not in by_k or all(k == fallback for k in ks.values()):
        return None
    reads = tuple(dict.fromkeys(read for read, _ in chosen if read))
    refs = [ref for _, ref in chosen]
    subject = refs[0] if len(refs) == 1 else f"({', '.join(refs)})"

    def values(cell: tuple[tuple[str, str], ...]) -> object:
        return cell[0][0] if len(cell) == 1 else tuple(value for value, _ in cell)

    groups, terms, given = [], [], []
    for k in sorted(set(ks.values()) - {fallback}, reverse=True):
        members = [cell for cell in ks if ks[cell] == k]
        listed = [values(cell) for cell in members]
        test = f"{subject} == {listed[0]!r}" if len(listed) == 1 else f"{subject} in {tuple(listed)!r}"
        groups.append((tuple(tuple(atom for _, atom in cell) for cell in members), by_k[k]))
        terms.append(f"{test} and {by_k[k]}")
        given += listed
    terms.append(f"{subject} not in {tuple(given)!r} and {by_k[fallback]}")
    text = " or ".join(terms)
    if reads:
        text = f"{' and '.join(reads)} and ({text})"
    names = " and ".join(NAMED.sub(r"\1", ref) for ref in refs)
    learned = ", ".join(f"{values(cell)!r}: {k}" for cell, k in sorted(ks.items()))
    reason = (f"kept: an allowance per item by {names}, learned from the labelled calls ({learned}): refuses calls "
              f"labelled 'refuse' that one allowance for every call does not; a {names} no labelled or "
              f"demonstrated call shows gets {fallback}, "
              + ("the allowance every call to allow meets" if fixed is not None else "the smallest of the table"))
    return Table(reads, tuple(groups), by_k[fallback], text, reason)


NAMED = re.compile(r"^self\.results\['\w+'\]\[\w+\]\['(\w+)'\]$")
"""A read's field named by its own name (`tier`)."""


