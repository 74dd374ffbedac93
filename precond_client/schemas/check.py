"""`POST /check-actions` and `POST /validate`: their bodies and answers."""

from __future__ import annotations

from pydantic import Field

from precond_client.schemas.calls import HISTORY_DESCRIPTION, PRECONDITIONS_DESCRIPTION, History, ToolCall, _UsesRules
from precond_client.schemas.common import MAX_CALLS, JudgedBy, Preconditions, StrictBody
from precond_client.schemas.next_action import (
    DECIDED_DESCRIPTION,
    RULE_STATUS_DESCRIPTION,
    Decisions,
    RuleStatus,
)


class CheckRequest(_UsesRules):
    preconditions: Preconditions = Field(default_factory=dict, description=PRECONDITIONS_DESCRIPTION)
    decided: Decisions = Field(default_factory=dict, description=DECIDED_DESCRIPTION)
    history: History = Field(description=HISTORY_DESCRIPTION)
    calls: list[str | ToolCall] = Field(
        min_length=1,
        max_length=MAX_CALLS,
        description="Proposed calls, each judged on its own copy of the state after the history "
        "(e.g. `system.REQUEST('cuisine')`), or tool calls `{\"name\", \"arguments\"}` over a spec from "
        "`precond convert openai` (the verdict's `call` is then the rendered `agent.<name>(...)`).",
    )


class CallVerdict(StrictBody):
    call: str
    action: str | None = Field(
        default=None, description="The action (`Class.method`) the call is a call of; absent when it is not one.")
    rule_status: RuleStatus | None = Field(default=None, description=RULE_STATUS_DESCRIPTION)
    allowed: bool = Field(
        description="true only when the call ran with every rule holding; a rule or call that raises gives "
        "false with `error` set (naming the rule and the exception), never a silent refusal or approval."
    )
    violations: list[str] = Field(default_factory=list, description="The rules that do not hold.")
    decided: dict[str, str] = Field(
        default_factory=dict,
        description="How each violated rule was decided, where the request (or its stored set) says: an 'assumed' "
        "rule may be a correlate a reviewer has not confirmed; 'unseen' refuses a never-demonstrated action.",
    )
    error: str | None = Field(
        default=None,
        description="Why the call could not be judged normally: an exception raised by the call or by a rule "
        "(named), or a call that is not a call of a spec method.",
    )


class CheckResponse(StrictBody):
    results: list[CallVerdict]
    history_violation: str | None = Field(
        default=None,
        description="Set when the history itself broke the preconditions: the first line whose call an action's "
        "rules did not allow, the call, and those rules. The history is taken as what happened: the calls are "
        "still judged after it.",
    )
    judged_by: JudgedBy = Field(
        default="sandbox",
        description="What judged the calls: `interpreter` when the spec is one a converter writes (`precond "
        "convert openai` or `sgd`, recognised from its structure) and every rule is one the restricted "
        "interpreter evaluates, so the gateway answered at once without running any of the request's text; "
        "`sandbox` when a worker ran the history and the rules in the sandbox. Both give the same verdicts.",
    )


class Blocked(StrictBody):
    action: str
    rule: str
    demonstration: int = Field(description="Index of the demonstration whose call the rule would have refused.")
    line: int | None = Field(default=None, description="Line of that call in the demonstration.")
    call: str | None = Field(default=None, description="The demonstrated call, as written.")


class ValidateResponse(StrictBody):
    blocked: list[Blocked] = Field(
        default_factory=list, description="Every demonstrated call a rule would have refused; empty: all pass."
    )
    unjudged: dict[str, str] = Field(
        default_factory=dict, description="Rules that could not be judged at all (`action: rule` → why)."
    )
    raised: dict[str, str] = Field(
        default_factory=dict,
        description="Rules that raise instead of answering true or false (`action: rule` → where, and the "
        "exception: e.g. `AttributeError: 'USER' object has no attribute 'afirmed'` for a misspelt name); a call "
        "at which a rule raises is refused, so they are in `blocked` too.",
    )
    occurrences: dict[str, int] = Field(
        default_factory=dict,
        description="Per rule judged (`action: rule`), the demonstrated calls of its action it was judged at: a "
        "rule written by hand that none of them refused is `validated` in the set's `decided`.",
    )
