"""`POST /next-action`: its options, the status of an action's rule, its answer."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Annotated, Literal

from pydantic import Field, StringConstraints, model_validator

from precond_client.schemas.calls import HISTORY_DESCRIPTION, PRECONDITIONS_DESCRIPTION, History, _UsesRules
from precond_client.schemas.common import (
    MAX_ACTION_CHARS,
    MAX_ACTIONS,
    MAX_ASSERTIONS_PER_ACTION,
    MAX_DEMONSTRATIONS,
    MAX_THOUGHT_CHARS,
    POLICY_PATTERN,
    Assertion,
    Preconditions,
    StrictBody,
)
from precond_client.schemas.infer import ModelInfo

NextActionMode = Literal["sample", "constrained"]
ChooseBy = Literal["action", "line"]


class NextActionOptions(StrictBody):
    mode: NextActionMode = Field(
        default="constrained",
        description="'constrained' (default, best on the dev numbers: docs/results.md): the sandbox judges every "
        "call the agent could make now (its actions × argument values from the spec, the history and the "
        "demonstrations) and the model chooses among the allowed ones by likelihood; nothing allowed is said "
        "(`nothing_allowed`). 'sample': the paper's Algorithm 1 (greedy, then random samples until one passes).",
    )
    choose_by: ChooseBy = Field(
        default="action",
        description="Mode 'constrained': how the model chooses among the allowed calls. 'action' (default): the "
        "likeliest allowed action first, then its arguments one at a time, as greedy decoding would; 'line': the "
        "likeliest whole allowed line (turn F1 +0.02 on the dev numbers, but it favours short lines such as "
        "`NOTIFY_SUCCESS()`, and GT compatibility drops from 0.987 to 0.972: docs/results.md).",
    )
    return_allowed: bool = Field(
        default=False,
        description="Return, with each predicted action, the calls the preconditions allow in its state (with "
        "the model's log-likelihood in mode 'constrained').",
    )
    max_attempts: int = Field(default=5, ge=1, le=50, description="Mode 'sample': greedy plus samples.")
    max_actions: int = Field(default=1, ge=1, le=20)
    preconditions_in_prompt: bool = False
    verify: bool = Field(
        default=True,
        description="Algorithm 1's verified sampling; false: the greedy line only (still never a non-action).",
    )
    fallback: Literal["none", "greedy"] = Field(
        default="none",
        description="When no attempt passes: 'none' (default) answers `call: null` with the rejected attempts; "
        "'greedy' answers the model's greedy call with `verified: false` (the paper's Algorithm 1), and only "
        "when that line is a call of an action.",
    )
    temperature: float = Field(default=0.8, ge=0.0, le=2.0)
    max_new_tokens: int = Field(default=32, ge=4, le=128)
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    think: bool = Field(
        default=False,
        description="ReAct: before each action the model writes a thought, a `# think: ...` comment line (greedy, "
        "one line, printable characters only, at most 400 characters; up to three in a row where it writes "
        "more), and the action is then chosen after them, "
        "verified as in either mode. Demonstrations may carry such lines (ReAct's hand-written thoughts); a "
        "comment never changes the state the preconditions are judged in.",
    )
    policy: str | None = Field(
        default=None, pattern=POLICY_PATTERN,
        description="The model that proposes the calls: null (default) the served code model, prompted; "
        "'adapter:<id>' or 'adapter:<id>@<version>' one of this tenant's trained policies (`POST /policies`: the "
        "code model fine-tuned on demonstrations), its latest version unless one is named. Another tenant's "
        "adapter is not found (404), as one that does not exist.",
    )

    @model_validator(mode="after")
    def _options_of_the_mode(self) -> NextActionOptions:
        """Options that only mean something when sampling are refused in mode 'constrained', never ignored."""
        if self.mode == "constrained":
            if not self.verify:
                raise ValueError("verify: false needs mode 'sample' (mode 'constrained' only returns allowed calls)")
            if self.fallback != "none":
                raise ValueError("fallback: 'greedy' needs mode 'sample' (mode 'constrained' answers "
                                 "`nothing_allowed` instead of a forbidden call)")
        elif self.choose_by != "action":
            raise ValueError("choose_by: 'line' needs mode 'constrained' (mode 'sample' decodes freely)")
        return self


Decisions = Annotated[
    dict[
        Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)],
        Annotated[dict[Assertion, Annotated[str, StringConstraints(max_length=20)]],
                  Field(max_length=MAX_ASSERTIONS_PER_ACTION)],
    ],
    Field(max_length=MAX_ACTIONS),
]


DECIDED_DESCRIPTION = (
    "How each rule was decided (action -> rule -> 'established' / 'assumed' / 'zero-shot' / 'unseen' / "
    "'transferred'; an inference's `evidence[action][rule].decided`), named again in the verdicts of the rules "
    "that refuse a call and read into every verdict's `rule_status`. A stored set fills it from its inference's "
    "report; a rule it does not label is 'given'."
)


RuleStatus = Literal["established", "assumed", "transferred", "zero-shot", "missing", "given"]
STATUS_OF_DECIDED: dict[str, RuleStatus] = {
    "established": "established", "assumed": "assumed", "transferred": "transferred", "zero-shot": "zero-shot",
    "unseen": "missing",
}
"""An inference's `decided` label as the status of the action it belongs to; any other label ('no evidence' or
'validated': a rule written by hand, or a request that sent none) is 'given'."""
WEAKEST_FIRST: tuple[RuleStatus, ...] = ("missing", "zero-shot", "transferred", "assumed", "given", "established")
RULE_STATUS_DESCRIPTION = (
    "What the verdict on this call rests on: how the rule of its action was decided (the weakest of its rules). "
    "'established': the demonstrations show it; 'assumed': a fact every demonstrated call shared that they cannot "
    "tell from a correlate (review it); 'transferred': a prior rule learned for other services, not refuted "
    "here; 'zero-shot': the code model's guess from the spec, the action never or too thinly demonstrated; "
    "'missing': no rule learned (an action never or too thinly demonstrated and no guess kept): every call "
    "allowed when the action has no rule at all, every call refused when its rule is the placeholder `False` "
    "(`options.unseen: 'refuse'`); 'given': the request's (or a reviewer's) own rules, with no inference's word "
    "on how they were decided. Absent when the call is not a call of one of the spec's actions."
)


def rule_status(rules: Sequence[str], decided: Mapping[str, str]) -> RuleStatus:
    """The status of an action whose rules are `rules`, from `decided` (rule -> label): the weakest, since a
    verdict is only as good as the least backed rule that made it; no rule at all is 'missing'. One function for
    the service's verdicts and the embedded guard's, so that both say the same."""
    if not rules:
        return "missing"
    statuses = {STATUS_OF_DECIDED.get(decided.get(rule, ""), "given") for rule in rules}
    return min(statuses, key=WEAKEST_FIRST.index)


class NextActionRequest(_UsesRules):
    preconditions: Preconditions = Field(
        default_factory=dict, description=PRECONDITIONS_DESCRIPTION + " Predicted calls are verified against them."
    )
    decided: Decisions = Field(default_factory=dict, description=DECIDED_DESCRIPTION)
    demonstrations: list[str] = Field(
        default_factory=list,
        max_length=MAX_DEMONSTRATIONS,
        description="Example trajectories shown to the model in its prompt (programs over the spec); their "
        "argument values are among the calls judged. Empty with `precondition_set`: the set's demonstrations.",
    )
    history: History = Field(description=HISTORY_DESCRIPTION)
    options: NextActionOptions = Field(
        default_factory=NextActionOptions, description="Sampling, verification and fallback."
    )


class Rejection(StrictBody):
    call: str
    action: str | None = Field(
        default=None, description="The action (`Class.method`) the call is a call of; absent when it is not one.")
    rule_status: RuleStatus | None = Field(default=None, description=RULE_STATUS_DESCRIPTION)
    violations: list[str] = Field(default_factory=list)
    reason: str | None = None


class AllowedCall(StrictBody):
    call: str
    score: float | None = Field(
        default=None, description="Mode 'constrained': the model's log-likelihood of the call's line (higher is "
        "likelier); null where it was not scored."
    )


class PredictedAction(StrictBody):
    call: str | None = Field(
        description="The action call; null: no verified action (every attempt is in `rejected`, `reason` says "
        "why), or nothing allowed (`nothing_allowed`). Never a line that is not a call of an action."
    )
    action: str | None = Field(
        default=None, description="The action (`Class.method`) of `call`; absent when `call` is null.")
    rule_status: RuleStatus | None = Field(default=None, description=RULE_STATUS_DESCRIPTION)
    verified: bool = Field(description="The call satisfies the preconditions after the history (run in the sandbox).")
    held: list[str] = Field(
        default_factory=list,
        description="The preconditions of the call's action that hold (all of them when `verified`).",
    )
    attempts: int = Field(description="Mode 'sample': model lines tried; mode 'constrained': calls judged.")
    rejected: list[Rejection] = Field(
        default_factory=list,
        description="Calls refused and why: the violated preconditions (`violations`) or the error.",
    )
    nothing_allowed: bool = Field(
        default=False,
        description="Mode 'constrained': no call the agent could make is allowed by the preconditions here "
        "(`call` is null; `rejected` lists every call judged, with the precondition that fails).",
    )
    allowed: list[AllowedCall] | None = Field(
        default=None, description="With `options.return_allowed`: the calls the preconditions allow in this state."
    )
    reason: str | None = Field(default=None, description="Why `call` is null, or why an unverified call is given.")
    thoughts: list[Annotated[str, Field(max_length=MAX_THOUGHT_CHARS)]] = Field(
        default_factory=list, max_length=3,
        description="With `options.think` (ReAct): what the model wrote as `# think: ...` lines before choosing "
        "this action (one, or up to three in a row); they stay in the history the next action of the turn is "
        "chosen after.",
    )


class NextActionResponse(StrictBody):
    actions: list[PredictedAction]
    mode: NextActionMode = "constrained"
    history_violation: str | None = Field(
        default=None,
        description="Set when the history itself breaks the preconditions: the first call that does, by line, "
        "and the rules that did not hold. The history is taken as what happened and the answer is still given "
        "(a flagged answer, not a 422): rules inferred from a few demonstrations can be stricter than the dialogs "
        "that occur.",
    )
    model: ModelInfo | None = None
