"""Amounts a call pays against a balance (precond/engine/candidates/tool_amounts.py), on a theatre box office
written from scratch: a member rebooks seats of a booking for other seats of the same show, the difference in
fares paid from a wallet of theirs (a voucher holds credit, a card none), or pays a fee from one."""

from __future__ import annotations

import ast
import json
from collections.abc import Mapping
from types import SimpleNamespace

from precond.convert.openai import convert
from precond.engine.candidates import tool_facts
from precond.engine.candidates.tool_relations import relations
from precond.engine.spec import parse_spec
from precond_client.guard import AGENT_SHAPE
from precond_client.rule_interpreter import Frame, Scope, compile_rule

PARAMS = {"get_booking": ("booking_id",), "get_member": ("member_id",), "get_show": ("show_id",),
          "rebook_seats": ("booking_id", "seat_ids", "new_seat_ids", "wallet_id"),
          "pay_fee": ("booking_id", "fee", "wallet_id")}
TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "array" if p.endswith("ids") else "number" if p == "fee" else "string"}
                   for p in params}, "required": list(params)}}} for name, params in PARAMS.items()]
WRITES = {"rebook_seats", "pay_fee"}


def call(tool: str, arguments: Mapping[str, object], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": tool, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": json.dumps(result)}]


def office_run(n: int, credit: float = 50, new_fare: float = 30) -> list[dict[str, object]]:
    """Booking B{n} of member m{n} holds seats s{n}a (fare 10) and s{n}b (fare 20) of show h{n}, whose seats
    s{n}c and s{n}d cost `new_fare`; the member's voucher v_{n} holds `credit`, their card c_{n} none. The member
    rebooks s{n}a for s{n}c (paying the difference with the voucher on even runs, the card on odd ones), then pays
    a fee of 5 with the voucher."""
    booking = {"booking_id": f"B{n}", "member_id": f"m{n}",
               "seats": [{"seat_id": f"s{n}a", "fare": 10}, {"seat_id": f"s{n}b", "fare": 20}]}
    member = {"wallets": {f"voucher_{n}": {"credit": credit}, f"card_{n}": {"brand": "visa"}}}
    show = {"seats": {f"s{n}{c}": {"fare": fare} for c, fare in (("a", 10), ("b", 20), ("c", new_fare),
                                                                   ("d", new_fare))}}
    wallet = f"voucher_{n}" if n % 2 == 0 else f"card_{n}"
    return [{"role": "user", "content": f"rebook B{n}"}, *call("get_booking", {"booking_id": f"B{n}"}, booking),
            *call("get_member", {"member_id": f"m{n}"}, member), *call("get_show", {"show_id": f"h{n}"}, show),
            {"role": "user", "content": "yes"},
            *call("rebook_seats", {"booking_id": f"B{n}", "seat_ids": [f"s{n}a"], "new_seat_ids": [f"s{n}c"],
                                   "wallet_id": wallet}, {"ok": True}),
            {"role": "user", "content": "yes"},
            *call("pay_fee", {"booking_id": f"B{n}", "fee": 5, "wallet_id": f"voucher_{n}"}, {"ok": True})]


def found(runs: list[list[dict[str, object]]], action: str) -> list[str]:
    converted = convert(runs, TOOLS, writes=WRITES)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    return [a for a in relations(facts, action, spec.methods[f"AGENT.{action}"].positional) if "<=" in a]


def judge(atom: str, action: str, args: tuple[object, ...], credit: object, new_fare: float = 30) -> bool:
    booking = {"member_id": "m1", "seats": [{"seat_id": "s1a", "fare": 10}, {"seat_id": "s1b", "fare": 20}]}
    wallets: dict[str, object] = {"voucher_1": {"credit": credit} if credit is not None else {}, "card_1": {}}
    results = {"get_booking": {"B1": booking}, "get_member": {"m1": {"wallets": wallets}},
               "get_show": {"h1": {"seats": {"s1a": {"fare": 10}, "s1c": {"fare": new_fare}}},
                            "h2": {"seats": {"t2a": {"fare": 99}}}}}
    state = SimpleNamespace(results=results, changes={}, errors={}, seen={}, last_ok=True,
                            user=SimpleNamespace(messages=1, last_said="yes"))
    return bool(compile_rule(atom, Scope(AGENT_SHAPE, PARAMS[action]))(Frame(state, args)))


def test_the_difference_in_prices_a_call_pays_is_covered_by_the_balance_of_the_wallet_it_names() -> None:
    [atom] = [a for a in found([office_run(n) for n in range(6)], "rebook_seats") if "new_seat_ids]) - sum(" in a]
    assert "sum(" in atom and "new_seat_ids" in atom and "['credit']" in atom, atom
    paying = ("B1", ["s1a"], ["s1c"], "voucher_1")
    assert judge(atom, "rebook_seats", paying, credit=20)  # 30 - 10: covered
    assert not judge(atom, "rebook_seats", paying, credit=19.5)  # not covered
    assert judge(atom, "rebook_seats", ("B1", ["s1a"], ["s1c"], "card_1"), credit=0)  # a card holds no credit
    assert judge(atom, "rebook_seats", paying, credit=None)  # neither does a voucher without the field
    assert not judge(atom, "rebook_seats", ("B1", ["s1a"], ["s1c"], "voucher_9"), credit=99)  # not the member's


def test_an_amount_argument_is_covered_by_the_balance_of_the_wallet_it_names() -> None:
    atoms = found([office_run(n) for n in range(6)], "pay_fee")
    [atom] = [a for a in atoms if "fee <=" in a]
    assert judge(atom, "pay_fee", ("B1", 5, "voucher_1"), credit=5)
    assert not judge(atom, "pay_fee", ("B1", 6, "voucher_1"), credit=5)


def test_a_balance_a_demonstrated_call_overdraws_is_not_proposed() -> None:
    overdrawn = [office_run(n) for n in range(5)] + [office_run(6, credit=10)]  # pays 20 from 10
    assert not [a for a in found(overdrawn, "rebook_seats") if "new_seat_ids]) - sum(" in a]
    assert not found([office_run(n, credit=10 * n) for n in range(1, 6, 2)], "rebook_seats")  # only cards paid
