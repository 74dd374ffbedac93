"""What the embedded guard's interpreter (`rule_interpreter`) charges for the work a rule does, before it does it.

A call's rules take at most `Frame.budget` steps, a step being at most about half a microsecond of work on the
slowest path: an item of a comprehension costs the expressions its body evaluates; a comparison, `in`, a subscript's
key, hashing into a set and `max`/`min` cost the full size of the values they walk (`weight`: every nested element,
a string per CHARS_PER_STEP characters, an integer per BITS_PER_STEP bits); integer arithmetic costs by the
operands' bits (`sum`: each addition, `added`), and an integer past MAX_INT_BITS is refused. Values the guard did
not build (a tool's result, or whoever feeds it) can be made to hash alike (`n` and `n + 2**61 - 1` do, as do tuples
of them): a set of them (`SetBuilder`) costs each comparison Python's set makes among them, found and charged before
the set is built, and each later lookup in it as many (`Frame.alike`); the keys a call's rules read from a table
that lacks them are kept by hash, a comparison charged each (`Frame.remember`). Over the budget, `WorkExceeded`: the
call is refused, never allowed. Standard library only, as the interpreter.
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

MAX_STEPS = 200_000
"""Steps one call's rules may take, each at most about half a microsecond of work: a rule linear in a long
conversation's results uses a few thousand."""
MAX_INT_BITS = 1 << 18
"""The largest integer (in bits) a rule may make or name. A JSON number is at most 4,300 digits (Python's
`int_max_str_digits`), about 14,300 bits; squaring past this is what a rule that burns CPU does."""
CHARS_PER_STEP = 128
"""Characters of a string compared, hashed or searched per step (some 3 ns a character, the slowest: `in`)."""
BITS_PER_STEP = 4096
"""Bits of an integer compared, hashed, added or negated per step."""
COLLECTIONS = (list, tuple, set, frozenset, dict)
SIZED = (*COLLECTIONS, str)
CONTAINER_TYPES = frozenset(COLLECTIONS)
SET_TYPES = frozenset((set, frozenset))
INT_TYPES = frozenset((int, bool))


class WorkExceeded(RuntimeError):
    """A call's rules ran past their step budget (or made an integer past MAX_INT_BITS): the call is refused,
    with this as the reason."""


class Cell:
    """One run of a comprehension: its variable, and the cell of the comprehension it runs in."""

    __slots__ = ("outer", "value")

    def __init__(self, outer: Cell | None) -> None:
        self.outer = outer
        self.value: Any = None


class Frame:
    """One call's evaluation: the state, the arguments by position, the keys its rules inserted into tables, the
    sets it built whose values hash alike, and the steps left of its budget."""

    __slots__ = ("alike", "args", "budget", "env", "inserted", "recent", "state")

    def __init__(self, state: object, args: Sequence[Any], budget: int = MAX_STEPS) -> None:
        self.state = state
        self.args = args
        self.inserted: dict[str, dict[int, list[Any]]] | None = None
        """Per table, the keys its rules read that it lacks, by hash: keys that hash alike cost a charged step
        each, where a set of them would cost uncharged probes."""
        self.env: Cell | None = None
        """The comprehension being evaluated (None outside any)."""
        self.alike: dict[int, tuple[Any, int]] = {}
        self.recent: tuple[tuple[Any, int], ...] = ()
        """The last two sets built here and their weights (`weigh`), known from their building: `{...} == {...}`
        compares the two it just built."""
        """Sets built here (by id, with the set) whose values hash alike: the most of one hash, which each lookup
        in the set may compare with."""
        self.budget = budget

    def charge(self, steps: int) -> None:
        self.budget -= steps
        if self.budget < 0:
            raise WorkExceeded(f"the rules took more than their budget of steps ({MAX_STEPS:,} a call): "
                               "refused, not judged")

    def remember(self, path: str, key: Any) -> None:
        """`table[key]` read where the table lacks the key: what the spec's defaultdict inserts, for this call."""
        if self.inserted is None:
            self.inserted = {}
        bucket = self.inserted.setdefault(path, {}).setdefault(hash(key), [])
        if not self._holds(bucket, key):
            bucket.append(key)

    def remembers(self, path: str, key: Any) -> bool:
        bucket = self.inserted.get(path, {}).get(hash(key)) if self.inserted is not None else None
        return bucket is not None and self._holds(bucket, key)

    def _holds(self, bucket: list[Any], key: Any) -> bool:
        self.charge(len(bucket) * weigh(key, self))
        return any(kept is key or kept == key for kept in bucket)


def too_large() -> WorkExceeded:
    return WorkExceeded(f"an integer of more than {MAX_INT_BITS:,} bits: refused, not judged")


def alike_of(value: Any, frame: Frame) -> int:
    """How many of a set's values one lookup may compare with (1 unless its values hash alike)."""
    if not frame.alike:
        return 1
    found = frame.alike.get(id(value))
    return found[1] if found is not None and found[0] is value else 1


def weigh(value: Any, frame: Frame) -> int:
    """What walking `value` (comparing, hashing it) costs in steps: each nested element one, a string one per
    CHARS_PER_STEP characters, an integer one per BITS_PER_STEP bits, a set's elements once more for each value
    one of its lookups may compare with. Counting stops past the budget left (the charge then refuses)."""
    kind = type(value)
    if kind is str:
        return 1 + len(value) // CHARS_PER_STEP
    if kind is int:
        return 1 + int(value.bit_length()) // BITS_PER_STEP
    if kind not in CONTAINER_TYPES:
        return 1
    for made, known in frame.recent:
        if made is value:
            return known
    limit, total, stack = frame.budget, 1, [value]
    while stack and total <= limit:
        container = stack.pop()
        items = [*container, *container.values()] if type(container) is dict else container
        total += len(items)
        if total > limit:
            return total
        for item in items:
            kind = type(item)
            if kind is str:
                total += len(item) // CHARS_PER_STEP
            elif kind is int:
                total += item.bit_length() // BITS_PER_STEP
            elif kind in CONTAINER_TYPES:
                stack.append(item)
        if type(container) in SET_TYPES and alike_of(container, frame) > 1:
            total += (alike_of(container, frame) - 1) * weigh(tuple(container), frame)
    return total


def compare_cost(sized: bool) -> Callable[[Any, Any, Frame], int]:
    """What `==`/`!=` (`sized`: lists, dicts and sets of different lengths are unequal at once) or an ordering
    costs: a scalar against a collection, or collections of unlike types, one step; else both sides' sizes."""

    def cost(left: Any, right: Any, frame: Frame) -> int:
        kind, other = type(left), type(right)
        if kind not in CONTAINER_TYPES or other not in CONTAINER_TYPES:
            if kind in CONTAINER_TYPES or other in CONTAINER_TYPES:
                return 1
            return weigh(left, frame) + weigh(right, frame) - 1
        if kind is not other and not (kind in SET_TYPES and other in SET_TYPES):
            return 1
        if sized and kind is not tuple and len(left) != len(right):
            return 1
        frame.charge(weigh(left, frame))  # before the other side is walked: the walks stop at the budget left
        return 1 + weigh(right, frame)

    return cost


def comparison_cost(op: ast.cmpop) -> Callable[[Any, Any, Frame], int] | None:
    """What a comparison costs (None: `is`, the one step of its node)."""
    if isinstance(op, ast.Is | ast.IsNot):
        return None
    if isinstance(op, ast.In | ast.NotIn):
        return membership_cost
    return compare_cost(sized=isinstance(op, ast.Eq | ast.NotEq))


def charged(test: Callable[[Any, Any], Any], cost: Callable[[Any, Any, Frame], int] | None
            ) -> Callable[[Any, Any, Frame], Any]:
    """The comparison `test`, its `cost` charged first (`compare_cost`, `membership_cost`)."""
    if cost is None:
        return lambda left, right, frame: test(left, right)

    def compare(left: Any, right: Any, frame: Frame) -> Any:
        frame.charge(cost(left, right, frame))
        return test(left, right)

    return compare


def compared(left: Callable[[Frame], Any], right: Callable[[Frame], Any], test: Callable[[Any, Any], Any],
             cost: Callable[[Any, Any, Frame], int] | None) -> Callable[[Frame], Any]:
    """One comparison of two values (the common form): `charged`'s charge and test without a call between."""
    if cost is None:
        return lambda frame: test(left(frame), right(frame))

    def compare(frame: Frame) -> Any:
        first, second = left(frame), right(frame)
        frame.charge(cost(first, second, frame))
        return test(first, second)

    return compare


def membership_cost(item: Any, container: Any, frame: Frame) -> int:
    """`item in container`: a list or tuple compares the item with each element (each comparison walks at most the
    item); a set or dictionary hashes it and compares it with the values that share its hash; a string is
    searched."""
    kind = type(container)
    if kind is list or kind is tuple:
        return 1 + len(container) * weigh(item, frame)
    if kind is dict or kind in SET_TYPES:
        return weigh(item, frame) * alike_of(container, frame)
    if kind is str:
        return 1 + (len(container) + (len(item) if type(item) is str else 0)) // CHARS_PER_STEP
    return 1


def charge_key(key: Any, frame: Frame) -> None:
    """A subscript's key other than a string (whose hash is computed once and kept with it) is hashed (a
    dictionary) or read (a list): a tuple or a large integer costs its size."""
    kind = type(key)
    if kind is tuple or (kind is int and key.bit_length() > BITS_PER_STEP):
        frame.charge(weigh(key, frame))


def weighed(items: Iterable[Any], frame: Frame) -> Iterator[Any]:
    """The items `max`/`min` compare, each charged its size as it comes (a generator's are made one by one)."""
    for item in items:
        frame.charge(weigh(item, frame))
        yield item


def added(items: Iterable[Any], frame: Frame) -> Iterator[Any]:
    """The items `sum` adds, each charged before it is added: a step, and an integer by the bits of the larger of it
    and the total so far (kept as a bound: a total grows a bit an addition at most)."""
    bits = 0
    for item in items:
        if type(item) is int:
            bits = max(bits, item.bit_length()) + 1
            frame.charge(1 + bits // BITS_PER_STEP)
        else:
            frame.charge(1)
        yield item


def built_size(value: Any) -> int:
    return len(value) if isinstance(value, SIZED) else 0


def arithmetic_cost(a: Any, b: Any, repeats: bool, frame: Frame) -> int:
    """Integers by their bits (a product by the product of their 64-bit words, refused at once when it would pass
    MAX_INT_BITS); what a sequence would become (`[0] * n`, `s + s`) before it is built; a set difference by the
    lookups it makes."""
    if type(a) in INT_TYPES and type(b) in INT_TYPES:
        bits: int = a.bit_length()
        other: int = b.bit_length()
        if repeats:
            if bits + other > MAX_INT_BITS + 1:
                raise too_large()
            return 1 + ((bits >> 6) * (other >> 6) >> 8)
        return 1 + max(bits, other) // BITS_PER_STEP
    if type(a) in SET_TYPES and type(b) in SET_TYPES:
        return 1 + weigh(a, frame) * alike_of(b, frame) + len(b)
    built = built_size(a) + built_size(b)
    if repeats and built:
        times = b if built_size(a) else a
        built = built * times if isinstance(times, int) and not isinstance(times, bool) and times > 0 else built
    return 1 + built


def call_cost(function: Callable[..., Any], values: list[Any], frame: Frame) -> int:
    """`len` one step; `all`/`any` an element each; `max`/`min` the size of what they compare (`sum`: `added`)."""
    if function is len:
        return 1
    if function is all or function is any:
        return 1 + sum(built_size(v) for v in values)
    if len(values) == 1:
        only = values[0]
        return 1 + (len(only) if type(only) is str else weigh(only, frame) if type(only) in CONTAINER_TYPES else 0)
    return 1 + sum(weigh(v, frame) for v in values)


class SetBuilder:
    """A set comprehension's values, each charged its size and hashed as Python's set hashes it when it comes (an
    unhashable one raises there); `build` finds the values that hash alike, charging each comparison Python's set
    would make among them, before the set makes those comparisons uncharged."""

    __slots__ = ("frame", "hashes", "values", "weights")

    def __init__(self, frame: Frame) -> None:
        self.frame = frame
        self.values: list[Any] = []
        self.hashes: list[int] = []
        self.weights: list[int] = []

    def add(self, value: Any) -> None:
        kind = type(value)
        if kind is list or kind is dict or kind is set:
            hash(value)  # TypeError: unhashable type, before anything is walked
        weight = weigh(value, self.frame)
        self.frame.charge(weight)
        self.hashes.append(hash(value))
        self.values.append(value)
        self.weights.append(weight)

    def build(self) -> set[Any]:
        alike = 1
        if len(set(self.hashes)) != len(self.hashes):  # hashes are distinct integers: else this set never probes
            groups: dict[int, list[int]] = {}
            for index, hashed in enumerate(self.hashes):
                groups.setdefault(hashed, []).append(index)
            alike = max(self._distinct(indexes) for indexes in groups.values() if len(indexes) > 1)
        made = set(self.values)
        if alike > 1:
            self.frame.alike[id(made)] = (made, alike)
        self.frame.recent = (*self.frame.recent[-1:], (made, (1 + sum(self.weights)) * alike))
        return made

    def _distinct(self, indexes: list[int]) -> int:
        """How many distinct values share one hash: a value is compared with each kept one until it equals one."""
        kept: list[Any] = []
        for index in indexes:
            value = self.values[index]
            for other in kept:
                self.frame.charge(self.weights[index])
                if other is value or other == value:
                    break
            else:
                kept.append(value)
        return len(kept)


