"""Where a tool call's arguments came from and which state it moves its record out of
(precond/engine/candidates/tool_sources.py, tool_transitions.py, precond/engine/judging/categorical.py), on
programs `precond/convert/openai.py` writes from a small card-services agent built here."""

from __future__ import annotations

import ast
import json
from pathlib import Path

from precond.convert.openai import convert
from precond.engine.candidates import tool_facts, tool_sources, tool_transitions
from precond.engine.candidates.tool_relations import runnable
from precond.engine.factory import build_engine
from precond.engine.judging import categorical
from precond.engine.judging.cautious import Choice
from precond.engine.judging.ranking import Candidate, Cluster
from precond.engine.spec import parse_spec
from precond.evaluation import tools_domain

CARDS = Path(__file__).resolve().parents[1] / "fixtures" / "tools_domains" / "cards"
TOOLS = [{"type": "function", "function": {"name": name, "parameters": {
    "properties": {p: {"type": "string"} for p in params}, "required": list(params)}}}
    for name, params in [("find_customer", ("email",)), ("verify", ("phone",)), ("get_profile", ("customer_id",)),
                         ("get_card", ("card_id",)), ("freeze", ("card_id",)), ("set_pin", ("card_id",))]]
WRITES = {"freeze", "set_pin"}


def call(name: str, arguments: dict[str, str], result: object) -> list[dict[str, object]]:
    return [{"role": "assistant", "tool_calls": [{"function": {"name": name, "arguments": json.dumps(arguments)}}]},
            {"role": "tool", "content": result if isinstance(result, str) else json.dumps(result)}]


def card_run(customer: str, card: str, status: str, write: str = "freeze", after: str = "frozen",
             asked: str | None = None) -> list[dict[str, object]]:
    """The customer found by email and verified, their profile and card read, then the write on the card."""
    return [{"role": "user", "content": "help"}, *call("find_customer", {"email": f"{customer}@x"}, customer),
            *call("verify", {"phone": "1"}, {"customer_id": customer, "verified": True}),
            *call("get_profile", {"customer_id": asked or customer}, {"customer_id": customer, "cards": [card]}),
            *call("get_card", {"card_id": card}, {"card_id": card, "status": status}),
            *call(write, {"card_id": card}, {"card_id": card, "status": after})]


def facts_of(runs: list[list[dict[str, object]]], demonstrated: int | None = None) -> tool_facts.ToolFacts:
    converted = convert(runs, TOOLS, writes=WRITES)
    spec = parse_spec(converted.spec)
    facts = tool_facts.read_facts(spec, "AGENT", [ast.parse(t.program) for t in converted.trajectories])
    facts.demonstrated = demonstrated
    return facts


def test_an_id_a_look_up_returned_and_an_id_field_of_a_read_are_where_an_argument_came_from() -> None:
    facts = facts_of([card_run("C1", "K1", "active"), card_run("C2", "K2", "active")])
    found = tool_sources.found(facts, "get_profile", ("self", "customer_id"))
    assert found == ["customer_id in self.seen['find_customer']",
                     "customer_id in [y['customer_id'] for y in self.seen['verify']]"]
    assert runnable(found, ("customer_id",)) == found  # the embedded guard runs them
    # a field that is not an id (`status`) is what the logs kept, not where an argument must come from
    assert all("status" not in atom for atom in tool_sources.provenance(facts, "freeze", ("self", "card_id")))


def test_a_labelled_run_does_not_erase_where_the_demonstrated_arguments_came_from() -> None:
    # the third run (a labelled one) reads another customer's profile: the condition that refuses it stays
    runs = [card_run("C1", "K1", "active"), card_run("C2", "K2", "active"),
            card_run("C1", "K1", "active", asked="C9")]
    assert tool_sources.found(facts_of(runs), "get_profile", ("self", "customer_id")) == []
    assert "customer_id in self.seen['find_customer']" in tool_sources.found(
        facts_of(runs, demonstrated=2), "get_profile", ("self", "customer_id"))


def test_the_state_every_demonstrated_call_moved_its_record_out_of_is_proposed() -> None:
    moved = "card_id in self.results['get_card'] and self.results['get_card'][card_id]['status'] in ('active',)"
    freezes = [card_run("C1", "K1", "active"), card_run("C2", "K2", "active")]
    assert tool_transitions.transitions(facts_of(freezes), "freeze", ("self", "card_id")) == [moved]
    assert runnable([moved], ("card_id",)) == [moved]
    # a write that leaves the status where it was, one call, or calls from two states: no transition
    kept = [card_run("C1", "K1", "active", "set_pin", "active"), card_run("C2", "K2", "active", "set_pin", "active")]
    assert tool_transitions.transitions(facts_of(kept), "set_pin", ("self", "card_id")) == []
    assert tool_transitions.transitions(facts_of(freezes[:1]), "freeze", ("self", "card_id")) == []
    mixed = [card_run("C1", "K1", "active"), card_run("C2", "K2", "blocked")]
    assert tool_transitions.transitions(facts_of(mixed), "freeze", ("self", "card_id")) == []


def test_a_transition_the_evidence_cannot_tell_from_its_read_is_kept_beside_it_assumed() -> None:
    read = "card_id in self.results['get_card']"
    moved = f"{read} and self.results['get_card'][card_id]['status'] in ('active',)"
    alike = f"{read} and self.results['get_card'][card_id]['status'] == 'active'"
    group = Cluster(tuple(Candidate(e, "enumerate", 0b101) for e in (read, alike, moved)))
    refined = categorical.refined(Choice([group], {read: "established"}))
    assert [c.representative.expression for c in refined.chosen] == [read, moved]
    assert refined.decided == {read: "established", moved: "assumed"}
    assert categorical.refinements(refined.notes) == {moved}
    assert categorical.refined(Choice([Cluster((group.members[0], group.members[1]))])).chosen[-1].members[0] \
        .expression == read  # an equality is not a transition: nothing is added


def test_the_cards_domain_learns_who_the_caller_is_and_which_state_a_change_needs() -> None:
    train, labels, _, _ = tools_domain.load(CARDS)
    engine = build_engine(with_model=False)
    plain = engine.infer(tools_domain.infer_request(train, labels, [])).preconditions
    assert "customer_id in [y['customer_id'] for y in self.seen['verify_identity']]" in plain[
        "AGENT.get_customer_profile"]
    for action, state in (("freeze_card", "active"), ("unfreeze_card", "frozen")):
        assert (f"card_id in self.results['get_card_details'] and self.results['get_card_details'][card_id]"
                f"['status'] in ({state!r},)") in plain[f"AGENT.{action}"]
    # the labels still teach the limit: a call over the card's maximum is refused by a rule of its own
    taught = engine.infer(tools_domain.infer_request(train, labels, labels)).preconditions
    assert any("new_limit <= self.results['get_card_details'][card_id]['max_limit']" in r
               for r in taught["AGENT.set_card_limit"])


def test_a_write_that_keeps_its_record_in_a_state_another_write_leaves_needs_that_state() -> None:
    # freezes move cards out of `active`; every pin change found its card active: the state is theirs too
    moved = "card_id in self.results['get_card'] and self.results['get_card'][card_id]['status'] in ('active',)"
    runs = [card_run("C1", "K1", "active"), card_run("C2", "K2", "active"),
            card_run("C3", "K3", "active", "set_pin", "active"), card_run("C4", "K4", "active", "set_pin", "active")]
    assert tool_transitions.transitions(facts_of(runs), "set_pin", ("self", "card_id")) == [moved]
    # a pin changed on a blocked card as well: the logs show it outside that state, so no condition
    runs[3] = card_run("C4", "K4", "blocked", "set_pin", "blocked")
    assert tool_transitions.transitions(facts_of(runs), "set_pin", ("self", "card_id")) == []


def test_an_argument_within_a_capacity_of_its_record_is_kept_beside_the_read() -> None:
    read = "card_id in self.results['get_card']"
    capped = f"{read} and new_limit <= self.results['get_card'][card_id]['max_limit']"
    current = f"{read} and new_limit >= self.results['get_card'][card_id]['limit']"  # a correlate: no capacity
    group = Cluster(tuple(Candidate(e, "enumerate", 0b11) for e in (read, capped, current)))
    refined = categorical.refined(Choice([group], {read: "assumed"}))
    assert [c.representative.expression for c in refined.chosen] == [read, capped]
