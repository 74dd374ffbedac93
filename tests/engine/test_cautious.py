"""The cautious criterion on small domains of its own, each built so that the paper's criteria get it wrong:
the guard must stay closed in the state the demonstrations never show."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import pytest

from precond.engine.engine import Engine
from precond.engine.judging.cautious import polarity
from precond.engine.judging.report import UNSEEN_RULE
from precond.sandbox import Sandbox
from precond_client.schemas import CheckRequest, InferOptions, InferRequest, InferResponse

CARD_SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.intent = defaultdict(lambda: False)
    self.informed = defaultdict(lambda: False)
    self.affirmed = False
  def INFORM_INTENT(self, intent): self.intent[intent] = True
  def INFORM(self, slot): self.informed[slot] = True
  def AFFIRM(self): self.affirmed = True

class SYSTEM:
  def __init__(self, user):
    self.user = user
    self.identity_verified = False
    self.blocked = None
  def REQUEST(self, slot): pass
  def VERIFY_IDENTITY(self): pass
  def CONFIRM(self): pass
  def BLOCK_CARD(self): pass
  def NOTIFY(self): pass
  def REPORT_FRAUD(self): pass
  def identity_result(self, ok): self.identity_verified = ok
  def block_result(self, ok): self.blocked = ok
"""


def _card_dialog(first: str, second: str) -> str:
    return "\n".join([
        "user = USER()", "system = SYSTEM(user)", "user.INFORM_INTENT('block_card')",
        f"system.REQUEST({first!r})", f"user.INFORM({first!r})", f"system.REQUEST({second!r})",
        f"user.INFORM({second!r})", "system.VERIFY_IDENTITY()", "system.identity_result(True)",
        "system.CONFIRM()", "user.AFFIRM()", "system.BLOCK_CARD()", "system.block_result(True)", "system.NOTIFY()",
    ]) + "\n"


CARD_DEMOS = [_card_dialog("name", "dob"), _card_dialog("dob", "name"), _card_dialog("name", "dob"),
              _card_dialog("dob", "name")]

def _service_spec(call: str, answer: str, result: str, extra: str = "") -> str:
    """A user who states an intent and gives slots, a system that asks, calls one service and reads its answer."""
    return f"""from collections import defaultdict
class USER:
  def __init__(self):
    self.intent = defaultdict(lambda: False)
    self.informed = defaultdict(lambda: False)
  def INFORM_INTENT(self, intent): self.intent[intent] = True
  def INFORM(self, slot): self.informed[slot] = True

class SYSTEM:
  def __init__(self, user):
    self.user = user
    self.{result} = None
  def REQUEST(self, slot): pass
  def {call}(self): pass
{extra}  def {answer}(self, value): self.{result} = value
"""


BANK_SPEC = _service_spec("LOOKUP_BALANCE", "balance_result", "balance", "  def INFORM_BALANCE(self): pass\n")


def _service_dialog(intent: str, slots: Sequence[str], service: Sequence[str]) -> str:
    steps = ["user = USER()", "system = SYSTEM(user)", f"user.INFORM_INTENT({intent!r})"]
    for slot in slots:
        steps += [f"system.REQUEST({slot!r})", f"user.INFORM({slot!r})"]
    return "\n".join([*steps, *service]) + "\n"


ACCOUNT = ("account", "pin")
SECURITY = ("dob", "answer1", "answer2")
LOOKUP = ("system.LOOKUP_BALANCE()", "system.balance_result(120)", "system.INFORM_BALANCE()")
BANK_DEMOS = [_service_dialog("balance", c, LOOKUP) for c in (ACCOUNT, SECURITY) * 3]

SEARCH_SPEC = _service_spec("SEARCH", "search_result", "results", "  def OFFER(self): pass\n")
SEARCH = ("system.SEARCH()", "system.search_result(3)", "system.OFFER()")
SEARCH_DEMOS = [_service_dialog("find_flight", s, SEARCH) for s in (("city", "date"), ("date", "city")) * 2]

SHOP_SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.intent = defaultdict(lambda: False)
    self.informed = defaultdict(lambda: False)
    self.selected = False
    self.thanked = False
    self.declined = False
  def INFORM_INTENT(self, intent): self.intent[intent] = True
  def INFORM(self, slot): self.informed[slot] = True
  def SELECT(self): self.selected = True
  def THANK(self): self.thanked = True
  def DECLINE(self): self.declined = True

class SYSTEM:
  def __init__(self, user):
    self.user = user
    self.success = None
  def REQUEST(self, slot): pass
  def SEARCH(self): pass
  def OFFER(self): pass
  def CONFIRM(self, slot): pass
  def BOOK(self): pass
  def REQ_MORE(self): pass
  def NOTIFY(self): pass
  def answer(self, ok): self.success = ok
"""


def _shop_dialog(ending: str) -> str:
    """The user gives both slots up front; the search answers; then the dialog ends one of three ways."""
    steps = ["user = USER()", "system = SYSTEM(user)", "user.INFORM_INTENT('book')", "user.INFORM('city')",
             "user.INFORM('date')", "system.SEARCH()"]
    if ending == "failed":
        steps += ["system.answer(False)", "system.REQ_MORE()"]
        return "\n".join(steps) + "\n"
    steps += ["system.answer(True)", "system.OFFER()", "user.SELECT()", "system.CONFIRM('city')",
              "system.CONFIRM('date')"]
    if ending == "declined":
        steps += ["user.DECLINE()", "system.REQ_MORE()"]
    else:
        steps += ["system.BOOK()", "system.answer(True)", "system.NOTIFY()", "user.THANK()", "system.REQ_MORE()"]
    return "\n".join(steps) + "\n"


SHOP_DEMOS = [_shop_dialog(e) for e in ("failed", "booked", "failed", "declined", "failed", "booked")]
SHOP_DEMOS_NO_FAILURE = [_shop_dialog(e) for e in ("booked", "declined", "booked", "declined", "booked", "declined")]


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


def _infer(engine: Engine, spec: str, demos: list[str], **options: Any) -> InferResponse:
    return engine.infer(InferRequest(spec=spec, demonstrations=demos,
                                     options=InferOptions(generators=["enumerate"], **options)))


def _allowed(engine: Engine, spec: str, rules: dict[str, list[str]], history: list[dict[str, Any]],
             call: str) -> bool:
    verdict = engine.check(CheckRequest(spec=spec, preconditions=rules, history=history, calls=[call])).results[0]
    assert verdict.error is None, verdict.error
    return verdict.allowed


def _events(*steps: tuple[str, str, list[Any]]) -> list[dict[str, Any]]:
    return [{"actor": actor, "act": act, "args": args} for actor, act, args in steps]


CONFIRMED_FIRST = _events(("user", "INFORM_INTENT", ["block_card"]), ("system", "CONFIRM", []),
                          ("user", "AFFIRM", []))
VERIFIED = _events(("user", "INFORM_INTENT", ["block_card"]), ("user", "INFORM", ["name"]),
                   ("user", "INFORM", ["dob"]), ("system", "VERIFY_IDENTITY", []),
                   ("system", "identity_result", [True]), ("system", "CONFIRM", []), ("user", "AFFIRM", []))


def test_identity_verified_before_every_confirmation_stays_required(engine: Engine) -> None:
    response = _infer(engine, CARD_SPEC, CARD_DEMOS)
    rules = response.preconditions
    assert "self.identity_verified" in rules["SYSTEM.BLOCK_CARD"]
    assert response.evidence["SYSTEM.BLOCK_CARD"]["self.identity_verified"].decided == "assumed"
    assert response.evidence["SYSTEM.BLOCK_CARD"]["self.user.affirmed"].decided == "established"
    assert not _allowed(engine, CARD_SPEC, rules, CONFIRMED_FIRST, "system.BLOCK_CARD()")
    assert _allowed(engine, CARD_SPEC, rules, VERIFIED, "system.BLOCK_CARD()")
    # the paper's criteria drop it: on the demonstrated points `affirmed` implies it (that is not implication)
    paper = _infer(engine, CARD_SPEC, CARD_DEMOS, ranking="recency").preconditions
    assert _allowed(engine, CARD_SPEC, paper, CONFIRMED_FIRST, "system.BLOCK_CARD()")


def test_two_alternative_credential_sets_are_learned_as_a_disjunction(engine: Engine) -> None:
    response = _infer(engine, BANK_SPEC, BANK_DEMOS)
    rules = response.preconditions
    (rule,) = [r for r in rules["SYSTEM.LOOKUP_BALANCE"] if " or " in r]
    report = next(c for c in response.candidates["SYSTEM.LOOKUP_BALANCE"] if c.assertion == rule)
    assert report.kept and report.reason and "disjunction" in report.reason

    def given(*slots: str) -> list[dict[str, Any]]:
        return _events(("user", "INFORM_INTENT", ["balance"]), *(("user", "INFORM", [s]) for s in slots))

    assert _allowed(engine, BANK_SPEC, rules, given(*ACCOUNT), "system.LOOKUP_BALANCE()")
    assert _allowed(engine, BANK_SPEC, rules, given(*SECURITY), "system.LOOKUP_BALANCE()")
    for half in (("pin",), ("account",), ("dob", "answer2"), ("answer1", "answer2")):
        assert not _allowed(engine, BANK_SPEC, rules, given(*half), "system.LOOKUP_BALANCE()"), half


def test_an_intent_stated_at_the_start_of_every_dialog_stays_required(engine: Engine) -> None:
    response = _infer(engine, SEARCH_SPEC, SEARCH_DEMOS)
    rules = response.preconditions
    assert response.evidence["SYSTEM.SEARCH"]["self.user.intent['find_flight']"].decided == "assumed"
    slots = _events(("user", "INFORM", ["city"]), ("user", "INFORM", ["date"]))
    assert not _allowed(engine, SEARCH_SPEC, rules, slots, "system.SEARCH()")
    assert _allowed(engine, SEARCH_SPEC, rules, _events(("user", "INFORM_INTENT", ["find_flight"])) + slots,
                    "system.SEARCH()")
    # recency drops the intent: true almost everywhere, so "not separated from chance"
    paper = _infer(engine, SEARCH_SPEC, SEARCH_DEMOS, ranking="recency").preconditions
    assert _allowed(engine, SEARCH_SPEC, paper, slots, "system.SEARCH()")


def test_a_never_demonstrated_action_is_refused_by_default_and_says_so(engine: Engine) -> None:
    response = _infer(engine, CARD_SPEC, CARD_DEMOS)
    assert response.preconditions["SYSTEM.REPORT_FRAUD"] == [UNSEEN_RULE]
    assert response.evidence["SYSTEM.REPORT_FRAUD"][UNSEEN_RULE].decided == "unseen"
    assert "SYSTEM.REPORT_FRAUD" in response.warnings
    assert not _allowed(engine, CARD_SPEC, response.preconditions, VERIFIED, "system.REPORT_FRAUD()")
    allowing = _infer(engine, CARD_SPEC, CARD_DEMOS, unseen="allow")
    assert allowing.preconditions["SYSTEM.REPORT_FRAUD"] == []
    assert "SYSTEM.REPORT_FRAUD" in allowing.warnings


def test_dialog_acts_keep_only_what_enabled_them(engine: Engine) -> None:
    """CONFIRM is answered by the user, not by a service: a phase there is not assumed."""
    response = _infer(engine, CARD_SPEC, CARD_DEMOS)
    assert all(e.decided == "established" for e in response.evidence["SYSTEM.CONFIRM"].values())


@pytest.mark.parametrize(("expression", "expected"), [
    ("self.user.informed['name']", "positive"), ("self.balance is not None", "positive"),
    ("obj in self.inventory", "positive"), ("not self.user.affirmed", "negative"),
    ("self.balance is None", "negative"), ("slot not in self.asked", "negative"), ("self.a != x", "negative"),
    ("self.a or not self.b", "negative"), ("def", "negative"),
])
def test_polarity_tells_established_facts_from_not_yet_conditions(expression: str, expected: str) -> None:
    assert polarity(expression) == expected


def test_a_refusal_says_how_the_refusing_rule_was_decided(engine: Engine) -> None:
    response = _infer(engine, CARD_SPEC, CARD_DEMOS)
    decided = {a: {rule: e.decided or "" for rule, e in rules.items()} for a, rules in response.evidence.items()}
    verdict = engine.check(CheckRequest(spec=CARD_SPEC, preconditions=response.preconditions, decided=decided,
                                        history=CONFIRMED_FIRST, calls=["system.BLOCK_CARD()"])).results[0]
    assert not verdict.allowed
    assert verdict.decided["self.identity_verified"] == "assumed"
    assert set(verdict.decided) == set(verdict.violations)


def test_a_confirmation_keeps_the_slots_it_confirms_given_long_before(engine: Engine) -> None:
    """Every demonstration gave city and date up front, so only the selection enabled the confirmation; a guard
    must still refuse to confirm a city the user never gave."""
    response = _infer(engine, SHOP_SPEC, SHOP_DEMOS)
    rules = response.preconditions
    assert response.evidence["SYSTEM.CONFIRM"]["self.user.informed['city']"].decided == "assumed"
    no_city = _events(("user", "INFORM_INTENT", ["book"]), ("user", "INFORM", ["date"]), ("system", "SEARCH", []),
                      ("system", "answer", [True]), ("user", "SELECT", []))
    given = [*_events(("user", "INFORM", ["city"])), *no_city]
    assert not _allowed(engine, SHOP_SPEC, rules, no_city, "system.CONFIRM('date')")
    assert _allowed(engine, SHOP_SPEC, rules, given, "system.CONFIRM('date')")
    paper = _infer(engine, SHOP_SPEC, SHOP_DEMOS, ranking="recency").preconditions
    assert _allowed(engine, SHOP_SPEC, paper, no_city, "system.CONFIRM('date')")
    # an offer speaks of what the search found, not of what the user said: no slot is assumed there
    assert all(e.decided == "established" for e in response.evidence["SYSTEM.OFFER"].values())


def test_anything_else_after_a_failure_a_thanks_or_a_decline_is_a_disjunction_of_that_news(engine: Engine) -> None:
    """`success is not None` held at every "anything else?" and was renewed at the failures; it would allow the
    question right after a successful search, which no demonstration shows. The failure itself (the service
    answered no: news, though a negative condition), the thanks and the decline are what enabled the calls."""
    response = _infer(engine, SHOP_SPEC, SHOP_DEMOS)
    rules = response.preconditions
    assert rules["SYSTEM.REQ_MORE"] == ["not self.success or self.user.thanked or self.user.declined"]
    searched = _events(("user", "INFORM_INTENT", ["book"]), ("user", "INFORM", ["city"]), ("system", "SEARCH", []),
                       ("system", "answer", [True]))
    failed = [*searched[:-1], *_events(("system", "answer", [False]))]
    assert not _allowed(engine, SHOP_SPEC, rules, searched, "system.REQ_MORE()")
    assert _allowed(engine, SHOP_SPEC, rules, failed, "system.REQ_MORE()")
    assert _allowed(engine, SHOP_SPEC, rules, [*searched, *_events(("user", "THANK", []))], "system.REQ_MORE()")
    paper = _infer(engine, SHOP_SPEC, SHOP_DEMOS, ranking="recency").preconditions
    assert _allowed(engine, SHOP_SPEC, paper, searched, "system.REQ_MORE()")


def test_what_the_user_said_before_their_yes_is_not_assumed_but_the_services_answers_are(engine: Engine) -> None:
    """The user's yes came right before every card block: it answers the confirmation of what they said before,
    so their earlier words are not kept as assumed rules (named in the warning instead); the identity check is
    the service's answer, which no yes replaces, and stays assumed."""
    response = _infer(engine, CARD_SPEC, CARD_DEMOS)
    rules = response.preconditions["SYSTEM.BLOCK_CARD"]
    assert set(rules) == {"self.user.affirmed", "self.identity_verified"}
    warning = response.warnings["SYSTEM.BLOCK_CARD"]
    assert "yes came before every call" in warning and "self.user.informed['name']" in warning
    identity_from_the_bank = _events(("user", "INFORM_INTENT", ["block_card"]), ("system", "VERIFY_IDENTITY", []),
                                     ("system", "identity_result", [True]), ("system", "CONFIRM", []),
                                     ("user", "AFFIRM", []))
    assert _allowed(engine, CARD_SPEC, response.preconditions, identity_from_the_bank, "system.BLOCK_CARD()")
    assert not _allowed(engine, CARD_SPEC, response.preconditions, CONFIRMED_FIRST, "system.BLOCK_CARD()")


def test_a_confirmation_seen_in_one_dialog_keeps_the_slots_it_confirms_beside_a_prior(engine: Engine) -> None:
    """Confirmed in one dialog only (too thin to establish anything), with another service's rule for the
    confirmation: that rule joins the slots the confirmations spoke of, assumed; it does not replace them."""
    one = [_shop_dialog("booked"), *(_shop_dialog("failed") for _ in range(3))]
    response = engine.infer(InferRequest(spec=SHOP_SPEC, demonstrations=one, options=InferOptions(
        generators=["enumerate"], prior_rules={"SYSTEM.CONFIRM": ["self.user.selected"]})))
    decided = {rule: e.decided for rule, e in response.evidence["SYSTEM.CONFIRM"].items()}
    assert decided["self.user.selected"] == "transferred"
    assert decided["self.user.informed['city']"] == decided["self.user.informed['date']"] == "assumed"
    selected_without_city = _events(("user", "INFORM_INTENT", ["book"]), ("user", "INFORM", ["date"]),
                                    ("system", "SEARCH", []), ("system", "answer", [True]), ("user", "SELECT", []))
    assert not _allowed(engine, SHOP_SPEC, response.preconditions, selected_without_city, "system.CONFIRM('date')")
