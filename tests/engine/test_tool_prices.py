"""Amounts priced per item (precond/engine/candidates/tool_conditions.py `scaled`): an integer argument equal to a
price times
the number of records a list holds, the call's own or one a read returned; proposed with the prices the calls
show, chosen only to separate labelled calls (precond/engine/judging/counterexamples.py), never kept from demonstrations
alone, and never over a count the reads keep or a list of references to what was read."""

from __future__ import annotations

import ast
import json
from collections.abc import Iterator
from typing import Any

import pytest

from precond.convert.openai import convert
from precond.engine.candidates import tool_conditions, tool_facts
from precond.engine.engine import Engine
from precond.engine.spec import parse_spec
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferRequest

TYPES = {"amount": "integer", "points": "integer", "lines": "array"}
TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": TYPES.get(p, "string")} for p in params}, "required": list(params)}}}
    for name, params in [("get_customer", ("customer_id",)), ("get_order", ("order_id",)),
                         ("list_products", ()), ("issue_voucher", ("customer_id", "amount")),
                         ("refund_order", ("order_id", "amount")), ("add_points", ("order_id", "points")),
                         ("quote", ("customer_id", "lines", "amount"))]]
VOUCHER = "AGENT.issue_voucher"
PRICE = ("any(amount == 20 * len(self.results['get_order'][x]['items']) for x in "
         "self.results['get_order'])")


def call(name: str, arguments: dict[str, object], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": name, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def voucher(tier: str, items: int, amount: int) -> list[dict[str, object]]:
    """A customer of `tier` whose order holds `items` items is sent a voucher of `amount` (the voucher is the
    5th message, its call on line 6 of the program)."""
    order = {"order_id": "o1", "status": "late", "items": [{"sku": f"s{k}", "colour": "red"} for k in range(items)]}
    return [{"role": "user", "content": "my order is late"},
            *call("get_customer", {"customer_id": "c1"}, {"customer_id": "c1", "tier": tier}),
            *call("get_order", {"order_id": "o1"}, order),
            *call("issue_voucher", {"customer_id": "c1", "amount": amount}, {})]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def labelled(runs: list[tuple[list[dict[str, object]], str]]) -> tuple[list[str], list[dict[str, Any]]]:
    converted = convert([r for r, _ in runs], TOOLS)
    line = next(n for n, text in enumerate(converted.trajectories[0].program.splitlines(), 1)
                if "issue_voucher(" in text)
    return [t.name for t in converted.trajectories], [
        {"program": t.program, "calls": [{"line": line, "verdict": verdict, "name": t.name}]}
        for t, (_, verdict) in zip(converted.trajectories, runs, strict=True)]


def infer(engine: Engine, demos: list[list[dict[str, object]]], counterexamples: list[dict[str, Any]]) -> Any:
    converted = convert(demos, TOOLS)
    return converted.spec, engine.infer(InferRequest.model_validate({
        "spec": converted.spec, "demonstrations": [t.program for t in converted.trajectories], "actions": [VOUCHER],
        "options": {"generators": ["enumerate"]}, "counterexamples": counterexamples}))


def test_the_price_labelled_calls_keep_is_chosen_and_judges_new_calls(engine: Engine) -> None:
    """Vouchers of 20 an item are allowed, others refused; every refused call also comes from a 'plus' customer,
    so the tier separates the labelled calls as well, but the price does it with one comparison, and it is the
    rule: a 'plus' customer's voucher of 60 for three items is allowed, one of 50 refused."""
    demos = [voucher("basic", 1, 20), voucher("basic", 2, 40), voucher("basic", 3, 60)]
    names, counterexamples = labelled([(voucher("plus", 1, 30), "refuse"), (voucher("plus", 2, 30), "refuse"),
                                       (voucher("plus", 3, 100), "refuse"), (voucher("basic", 2, 40), "allow")])
    spec, inferred = infer(engine, demos, counterexamples)
    assert PRICE in inferred.preconditions[VOUCHER]
    assert not any("tier" in rule for rule in inferred.preconditions[VOUCHER])
    assert sorted(inferred.evidence[VOUCHER][PRICE].refuses) == sorted(names[:3])
    lines = convert([voucher("plus", 3, 60)], TOOLS).trajectories[0].program.splitlines()
    at = next(n for n, text in enumerate(lines) if "issue_voucher(" in text)
    verdicts = engine.check(CheckRequest(spec=spec, preconditions=inferred.preconditions,
                                         history="\n".join(lines[:at]) + "\n",
                                         calls=[lines[at], lines[at].replace("60)", "50)")])).results
    assert [v.allowed for v in verdicts] == [True, False]


def test_a_price_every_demonstration_meets_is_not_kept_without_labels(engine: Engine) -> None:
    _, inferred = infer(engine, [voucher("basic", 1, 20), voucher("basic", 2, 40), voucher("plus", 3, 60)], [])
    assert not any("* len(" in rule for rule in inferred.preconditions[VOUCHER])


def scaled(runs: list[list[dict[str, object]]], action: str) -> list[str]:
    converted = convert(runs, TOOLS)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    return tool_conditions.scaled(facts, action, spec.methods[f"AGENT.{action}"].positional)


def test_prices_are_read_off_the_calls_over_lists_of_records_of_their_own() -> None:
    """A refund names its order: the price is over that order's items (20 at one call, 20 and 10 at the other);
    the order's payments name the customer's cards and its lines the products a read listed, so neither is
    priced; a list argument of the call's own is; a count the order keeps (`points`) never is."""
    order = {"order_id": "o1", "points": 3, "items": [{"sku": "s1"}, {"sku": "s2"}],
             "payments": [{"card_id": "card_7"}], "lines": [{"product_id": "p1"}]}
    customer = {"customer_id": "c1", "cards": {"card_7": {"kind": "visa"}}}
    runs = [[{"role": "user", "content": "refund"},
             *call("get_customer", {"customer_id": "c1"}, customer),
             *call("list_products", {}, [{"product_id": "p1", "name": "lamp"}]),
             *call("get_order", {"order_id": "o1"}, order),
             *call("refund_order", {"order_id": "o1", "amount": amount}, {}),
             *call("add_points", {"order_id": "o1", "points": 4}, {}),
             *call("quote", {"customer_id": "c1", "lines": [{"sku": "s1"}, {"sku": "s2"}], "amount": amount}, {})]
            for amount in (40, 20)]
    refund = scaled(runs, "refund_order")
    items = "order_id in self.results['get_order'] and amount == {} * len(self.results['get_order'][order_id]['items'])"
    assert refund == [items.format(10), items.format(20)]
    assert scaled(runs, "add_points") == []
    assert scaled(runs, "quote")[:2] == ["amount == 10 * len(lines)", "amount == 20 * len(lines)"]


def test_prices_that_each_fit_some_calls_to_allow_are_not_joined(engine: Engine) -> None:
    """Vouchers of 20 an item and of 30 an item are both allowed, and nothing else tells the calls apart: no one
    price holds at every call to allow, and a disjunction of prices, each fitting some of them, would be the
    amounts fitted one by one; no price is learned."""
    demos = [voucher("basic", 1, 20), voucher("basic", 2, 60), voucher("basic", 3, 60)]
    _, counterexamples = labelled([(voucher("basic", 1, 25), "refuse"), (voucher("basic", 2, 50), "refuse"),
                                   (voucher("basic", 2, 40), "allow")])
    _, inferred = infer(engine, demos, counterexamples)
    assert not any("* len(" in rule for rule in inferred.preconditions[VOUCHER])
