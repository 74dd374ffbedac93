"""The embedded guard's interpreter on the forms the enumerator writes for collections and dates (tuples, list,
set and generator comprehensions, `all`/`any`): the same answers and the same exceptions as Python, which the
sandbox runs; a comprehension's variable never leaks into the next rule."""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import pytest

from precond_client.guard import AGENT_SHAPE
from precond_client.rule_interpreter import Frame, OutsideGrammar, Scope, WorkExceeded, compile_rule

R = "self.results['get_reservation_details'][reservation_id]"
FLIGHTS = [{"flight_number": "HAT1", "date": "2024-05-20"}, {"flight_number": "HAT2", "date": "2024-05-21"}]
RULES = [
    f"{{(x['flight_number'], x['date']) for x in flights}} == "
    f"{{(x['flight_number'], x['date']) for x in {R}['flights']}}",
    f"{{(x['flight_number'],) for x in flights}} != {{(x['flight_number'],) for x in {R}['flights']}}",
    f"all(x['date'] >= '2024-05-15' for x in {R}['flights'])",
    f"any(x['date'] < '2024-05-15' for x in {R}['flights'])",
    "len([x for x in payment_methods if 'certificate_' in x['payment_id']]) <= 1",
    f"all(x['payment_id'] in {R}['payment_methods'] for x in payment_methods)",
    f"all(x['missing'] >= '2024-05-15' for x in {R}['flights'])",  # raises KeyError, as in the sandbox
    f"any(x['date'] < '2024-05-15' or x['missing'] for x in {R}['flights'])",  # stops where Python stops
    # the arithmetic a policy states: free bags per passenger, the rest paid
    f"{R}['nonfree_baggages'] == max(0, {R}['total_baggages'] - 2 * len(flights))",
    "min(len(flights), 3) + 1 - len(payment_methods) >= 0",
    f"{R}['total_baggages'] - {R}['missing'] >= 0",  # raises KeyError, as in the sandbox
    f"len(flights) * {R}['flights'] == {R}['flights'] + {R}['flights']",  # a sequence repeated, as Python does
    "max(flights) == 0",  # raises TypeError (dicts are not ordered), as in the sandbox
    # a total: the prices of a list, against a balance
    f"sum([len(x['date']) for x in {R}['flights']]) - {R}['total_baggages'] <= 17",
    "sum(len(x['payment_id']) for x in payment_methods) >= 13",  # a generator's items, as they come
    f"sum(({R}['total_baggages'], 0.1, 0.2, len(flights))) > 6.3",  # floats summed as Python sums them
    "sum([x['date'] for x in flights]) == 0",  # raises TypeError (0 + a string), as in the sandbox
    f"sum({R}['total_baggages']) > 0",  # raises TypeError (an int is not iterable), as in the sandbox
]


class State:
    def __init__(self, reservation: dict[str, Any]) -> None:
        self.results: defaultdict[str, dict[Any, Any]] = defaultdict(dict)
        self.results["get_reservation_details"]["R1"] = reservation
        self.user, self.changes, self.errors, self.last_ok = None, {}, {}, True


def python(rule: str, state: State, args: dict[str, Any]) -> tuple[str, Any]:
    """Inside a function of the parameters, as the sandbox compiles a rule (a comprehension sees them)."""
    function = eval(f"lambda self, reservation_id, flights, payment_methods: ({rule})", {})  # the test's own rules
    try:
        return "value", function(state, **args)
    except Exception as exc:
        return "raised", type(exc).__name__


def interpreted(rule: str, state: State, args: dict[str, Any]) -> tuple[str, Any]:
    evaluate = compile_rule(rule, Scope(AGENT_SHAPE, ("reservation_id", "flights", "payment_methods")))
    try:
        return "value", evaluate(Frame(state, [args["reservation_id"], args["flights"], args["payment_methods"]]))
    except Exception as exc:
        return "raised", type(exc).__name__


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("flown", [False, True])
@pytest.mark.parametrize("certificates", [1, 2])
def test_collection_and_date_forms_answer_as_python(rule: str, flown: bool, certificates: int) -> None:
    flights = [{**FLIGHTS[0], "date": "2024-05-01"}, FLIGHTS[1]] if flown else FLIGHTS
    state = State({"flights": flights, "payment_methods": {"certificate_1": {}, "credit_card_2": {}},
                   "total_baggages": 3 + certificates, "nonfree_baggages": 1})
    args = {"reservation_id": "R1", "flights": FLIGHTS,
            "payment_methods": [{"payment_id": f"certificate_{n}"} for n in range(certificates)]}
    assert interpreted(rule, state, args) == python(rule, state, args)


def test_a_comprehension_variable_is_bound_only_inside_it() -> None:
    scope = Scope(AGENT_SHAPE, ("flights",))
    with pytest.raises(OutsideGrammar, match="neither `self` nor a parameter"):
        compile_rule("[x for x in flights] and x", scope)
    with pytest.raises(OutsideGrammar, match="one `for` only"):
        compile_rule("[x for x in flights for y in flights]", scope)
    frame = Frame(State({}), [FLIGHTS])
    assert compile_rule("[x['date'] for x in flights]", scope)(frame) == ["2024-05-20", "2024-05-21"]
    assert frame.env is None


def test_what_arithmetic_would_build_is_charged_before_it_is_built() -> None:
    scope = Scope(AGENT_SHAPE, ("flights",))
    with pytest.raises(OutsideGrammar, match="Pow"):
        compile_rule("len(flights * 10 ** 12) > 0", scope)
    repeated = compile_rule("len(flights * 1000000000000) > 0", scope)
    with pytest.raises(WorkExceeded):
        repeated(Frame(State({}), [FLIGHTS]))  # charged, never built
    assert compile_rule("len(flights * 3) == 6", scope)(Frame(State({}), [FLIGHTS]))
    with pytest.raises(OutsideGrammar, match="Div"):
        compile_rule("len(flights) / 2 > 0", scope)


def test_a_sum_is_charged_each_item_and_takes_one_argument() -> None:
    scope = Scope(AGENT_SHAPE, ("flights",))
    with pytest.raises(OutsideGrammar, match="one argument"):
        compile_rule("sum(flights, []) == []", scope)  # a start would concatenate lists: quadratic
    total = compile_rule("sum(flights) >= 0", scope)
    assert total(Frame(State({}), [list(range(1000))]))
    with pytest.raises(WorkExceeded):
        total(Frame(State({}), [[1] * 1000], budget=500))  # an item a step: past the budget, refused
    with pytest.raises(WorkExceeded):  # an integer of 2**17 bits added 100 times: its bits charged each time
        total(Frame(State({}), [[1 << (1 << 17)] * 100], budget=2000))
