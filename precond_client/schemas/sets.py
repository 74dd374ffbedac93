"""Precondition sets: creating, editing, re-inferring and reading a set's versions."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StringConstraints

from precond_client.schemas.calls import HISTORY_DESCRIPTION, PRECONDITIONS_DESCRIPTION, History, ToolCall
from precond_client.schemas.check import ValidateResponse
from precond_client.schemas.common import (
    MAX_ACTION_CHARS,
    MAX_ACTIONS,
    MAX_ASSERTION_CHARS,
    MAX_DEMONSTRATIONS,
    MAX_SOURCE_CHARS,
    SPEC_DESCRIPTION,
    Assertion,
    Preconditions,
    StrictBody,
)
from precond_client.schemas.infer import CallVerdictLabel, CandidateReport, Counterexamples, InferOptions, RuleEvidence

MAX_SET_EDITS = 64
EditOp = Literal["add", "remove", "require", "reject"]


class RuleEdit(StrictBody):
    op: EditOp = Field(description="'add' a rule; 'remove' one; 'require' one (re-inference keeps it); 'reject' "
                       "one (removed, and re-inference never brings it back).")
    action: str = Field(max_length=MAX_ACTION_CHARS, description="`Class.method`.")
    rule: Assertion = Field(description="The rule: a Python expression, without `assert`.")


MAX_REPORTED_CANDIDATES = 2_000
"""Candidates per action an inference's report may carry into a set (an SGD action gets 60-90)."""

Evidence = Annotated[
    dict[Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)], dict[Assertion, RuleEvidence]],
    Field(max_length=MAX_ACTIONS),
]
Candidates = Annotated[
    dict[
        Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)],
        Annotated[list[CandidateReport], Field(max_length=MAX_REPORTED_CANDIDATES)],
    ],
    Field(max_length=MAX_ACTIONS),
]
EVIDENCE_DESCRIPTION = (
    "From an inference: its `evidence` (per action, per kept rule), kept with the rules so that a reviewer sees "
    "why each rule is there (the review page, /ui/, shows it)."
)
CANDIDATES_DESCRIPTION = (
    "From an inference: its `candidates`, each with why it was kept or dropped (the alternatives a reviewer may "
    "prefer)."
)
WARNINGS_DESCRIPTION = "From an inference: its `warnings` per action (e.g. no demonstration calls it)."


class PreconditionSetCreate(StrictBody):
    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS, description=SPEC_DESCRIPTION)
    preconditions: Preconditions = Field(
        default_factory=dict,
        description=PRECONDITIONS_DESCRIPTION + " From an inference: its `preconditions` as returned. At least "
        "one rule: a set without any would allow every call, so it is refused (422; to learn rules from "
        "demonstrations, `POST /infer-preconditions` first).",
    )
    demonstrations: list[str] = Field(
        default_factory=list, max_length=MAX_DEMONSTRATIONS,
        description="Demonstrations the rules must allow; every version is checked against them (in the sandbox).",
    )
    evidence: Evidence = Field(default_factory=dict, description=EVIDENCE_DESCRIPTION)
    candidates: Candidates = Field(default_factory=dict, description=CANDIDATES_DESCRIPTION)
    warnings: dict[Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)],
                   Annotated[str, StringConstraints(max_length=MAX_ASSERTION_CHARS)]] = Field(
        default_factory=dict, max_length=MAX_ACTIONS, description=WARNINGS_DESCRIPTION)
    force: bool = Field(default=False, description="Store even when a rule blocks a demonstrated call.")


class PreconditionSetEdit(StrictBody):
    edits: list[RuleEdit] = Field(min_length=1, max_length=MAX_SET_EDITS)
    base_version: int | None = Field(
        default=None, ge=1, description="The version these edits were made on; 409 when it is no longer the latest."
    )
    force: bool = Field(default=False, description="Store even when a rule blocks a demonstrated call.")


class PreconditionSetReinfer(StrictBody):
    demonstrations: list[str] = Field(
        min_length=1, max_length=MAX_DEMONSTRATIONS,
        description="New demonstrations (programs over the set's spec). Inference runs on the set's stored "
        "demonstrations and these; the new version stores both (duplicates once).",
    )
    actions: list[str] | None = Field(
        default=None, max_length=256,
        description="Actions (`Class.method`) to re-infer; default: every stub method of the spec. The rules of "
        "the others stay as they are.",
    )
    options: InferOptions = Field(default_factory=InferOptions, description="How candidates are made and ranked.")
    base_version: int | None = Field(
        default=None, ge=1, description="The version to re-infer from; 409 when it is no longer the latest."
    )
    force: bool = Field(default=False, description="Store even when a new demonstration breaks a required rule "
                        "(the rule is kept; `validation` reports what it blocks).")


class SetCounterexample(StrictBody):
    """A judged call a reviewer labels: after this history, this call must be refused (or allowed)."""

    history: History = Field(description=HISTORY_DESCRIPTION)
    call: str | ToolCall = Field(description="The call, as `/check-actions` takes it.")
    verdict: CallVerdictLabel = Field(description="'refuse': it should have been refused; 'allow': it should have "
                                      "been allowed.")
    actions: list[str] | None = Field(
        default=None, max_length=256,
        description="Actions (`Class.method`) to re-infer; default: the call's action alone. The rules of the "
        "others stay as they are.",
    )
    options: InferOptions = Field(default_factory=InferOptions, description="How candidates are made and ranked.")
    base_version: int | None = Field(
        default=None, ge=1, description="The version the call was judged with; 409 when it is no longer the latest."
    )
    force: bool = Field(default=False, description="Store even when a demonstration breaks a required rule.")


class RuleChange(StrictBody):
    action: str
    rule: str
    reason: str | None = Field(default=None, description="Why: the candidate's reason from the inference, or why "
                               "a rule of the base version is gone.")


class SetDiff(StrictBody):
    """What a re-inference changed, against the version it started from."""

    base_version: int
    added: list[RuleChange] = Field(default_factory=list, description="Inferred now, not in the base version.")
    removed: list[RuleChange] = Field(
        default_factory=list, description="In the base version, gone now, each with the reason it was dropped.")
    kept: list[RuleChange] = Field(default_factory=list, description="In both, inferred again.")
    required_kept: list[RuleChange] = Field(
        default_factory=list, description="Marked required: kept whatever the inference says.")
    rejected_suppressed: list[RuleChange] = Field(
        default_factory=list, description="Inferred again, but marked rejected: left out.")
    new_demonstrations: int = Field(default=0, description="Demonstrations added by this re-inference.")


class PreconditionSet(StrictBody):
    id: str
    version: int = Field(description="This version; versions are immutable.")
    latest: int = Field(description="The set's latest version.")
    reference: str = Field(description="`id@version`: what `precondition_set` accepts.")
    created: str = Field(description="When this version was made (UTC, ISO 8601).")
    spec: str
    preconditions: dict[str, list[str]]
    demonstrations: list[str] = Field(default_factory=list)
    required: dict[str, list[str]] = Field(default_factory=dict, description="Rules marked required.")
    rejected: dict[str, list[str]] = Field(default_factory=dict, description="Rules marked rejected.")
    edits: list[RuleEdit] = Field(default_factory=list, description="The edits that made it from the version before.")
    validation: ValidateResponse | None = Field(
        default=None, description="Rules checked against the demonstrations: what they block (kept only with force)."
    )
    diff: SetDiff | None = Field(
        default=None, description="For a version made by re-inference: what changed against its base version.")
    warnings: dict[str, str] = Field(
        default_factory=dict,
        description="Per action whose rule is empty (every call allowed) or not backed by the demonstrations, why: "
        "no rule, a reviewer rejected its only rules, or (a version made by re-inference) the inference's warning.")
    evidence: dict[str, dict[str, RuleEvidence]] = Field(
        default_factory=dict, description="The inference's evidence per action and rule (carried to later "
        "versions): occurrences, holds, exceptions, confidence.")
    candidates: dict[str, list[CandidateReport]] = Field(
        default_factory=dict, description="The inference's candidates per action, kept or dropped, with why.")
    counterexamples: list[Counterexamples] = Field(
        default_factory=list, description="The calls reviewers labelled (`POST /precondition-sets/{id}/"
        "counterexamples`), each a run of its history and the call: every re-inference learns with them, and a "
        "rule's `evidence[...].refuses` names those it refuses.")
    decided: dict[str, dict[str, str]] = Field(
        default_factory=dict, description="How each rule of this version was decided: 'established' (the "
        "demonstrations back it), 'assumed' (held at fewer than 3 demonstrated calls, or judged a requirement by "
        "the code model where the evidence left it open), 'zero-shot' (never demonstrated: the code model's "
        "guess), 'unseen' (never demonstrated and no guess: the placeholder `False`), 'transferred', or "
        "'validated' (written by hand, and no demonstrated call of its action refused by it: `validation."
        "occurrences` says how many), 'no evidence' (written by hand, its action never demonstrated or a call "
        "refused, or stored without an inference's report). The ones that need a human "
        "are the assumed and zero-shot rules.")


class PreconditionSetSummary(StrictBody):
    """One line of `GET /precondition-sets`: what a reviewer needs to pick a set, without its programs."""

    id: str
    actions: list[str] = Field(description="The actions the set knows: with rules, reported by its inference, or "
                               "with rejected rules.")
    reference: str = Field(description="`id@latest`.")
    latest: int = Field(description="The set's latest version, which the counts describe.")
    created: str = Field(description="When version 1 was made (UTC, ISO 8601).")
    updated: str = Field(description="When the latest version was made.")
    rules: int = Field(description="Rules in the latest version.")
    assumed: int = Field(description="Rules decided 'assumed'.")
    zero_shot: int = Field(description="Rules decided 'zero-shot'.")
    no_evidence: int = Field(description="Rules with no evidence (by hand, or stored without a report).")
    required: int = 0
    rejected: int = 0


class PreconditionSetList(StrictBody):
    sets: list[PreconditionSetSummary] = Field(description="Newest first (by creation).")
    total: int = Field(description="The tenant's sets.")
    offset: int
    limit: int
    next_offset: int | None = Field(default=None, description="The `offset` of the next page; null on the last.")
