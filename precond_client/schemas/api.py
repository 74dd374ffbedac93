"""Bodies of the three operations (infer, next-action, check) and of jobs and errors.

They live here, not in `precond/gateway/` or `precond/worker/`, because the CLI, the gateway, the queue payloads and the
engine all speak them: a field renamed in one place must fail everywhere at once.
Size bounds are part of the contract: they turn hostile inputs into 422s before any work is queued.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    StringConstraints,
    Tag,
    WithJsonSchema,
    model_validator,
)

MAX_SOURCE_CHARS = 200_000
MAX_DEMONSTRATIONS = 200
MAX_ASSERTIONS_PER_ACTION = 32
MAX_ASSERTION_CHARS = 1_000
MAX_CALLS = 64
MAX_CALL_CHARS = 1_000
MAX_THOUGHT_CHARS = 400
ADAPTER_ID_PATTERN = r"ad_[0-9a-f]{24}"
ADAPTER_REFERENCE = rf"^({ADAPTER_ID_PATTERN})(?:@([1-9][0-9]{{0,8}}))?$"
"""A stored trained policy: its id (the latest version) or `id@version`."""
POLICY_PATTERN = rf"^adapter:{ADAPTER_REFERENCE[1:]}"
"""A trained policy as `/next-action` names it: a stored adapter of the tenant, its latest or a given version."""

MAX_TOLERANCE = 0.5
DEFAULT_TOLERANCE = 0.05
DEFAULT_ANSWER_SLIPS = 0.3
MAX_LISTED_EXCEPTIONS = 20

Generator = Literal["model", "enumerate"]
Ranking = Literal["cautious", "subsumption", "recency", "marginal"]
Unseen = Literal["refuse", "allow"]
Decided = Literal["established", "assumed", "zero-shot", "unseen", "transferred"]
ModelFor = Literal["thin", "all"]
Listed = Literal["all", "kept", "none"]
JudgedBy = Literal["interpreter", "sandbox"]

SourceText = Field(max_length=MAX_SOURCE_CHARS)


class StrictBody(BaseModel):
    """Unknown fields are errors: a typo in an option must not silently fall back to a default."""

    model_config = ConfigDict(extra="forbid")

    @model_validator(mode="before")
    @classmethod
    def _first_unknown_field_only(cls, data: Any) -> Any:
        return _first_unknown_field_only(data, cls.model_fields)


def _first_unknown_field_only(data: Any, fields: Mapping[str, Any]) -> Any:
    """Only the first unknown field is reported: pydantic builds an error object per unknown field, so 400,000
    of them in a 4 MB body cost the gateway 500 MB for one 422 that quotes only the first."""
    if isinstance(data, dict) and len(data) > len(fields):
        first = next((key for key in data if key not in fields), None)
        data = {key: value for key, value in data.items() if key in fields or key == first}
    return data


MAX_ACTIONS = 256
MAX_ACTION_CHARS = 200
Assertion = Annotated[str, StringConstraints(max_length=MAX_ASSERTION_CHARS)]
Preconditions = Annotated[
    dict[
        Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)],
        Annotated[list[Assertion], Field(max_length=MAX_ASSERTIONS_PER_ACTION)],
    ],
    Field(max_length=MAX_ACTIONS),
]
"""Action (`Class.method`) → assertions; every bound is enforced here, before any work is queued."""

SET_REFERENCE = r"^ps_[0-9a-f]{24}(@[1-9][0-9]{0,8})?$"
MAX_PRIOR_RULES = 512
"""Prior rules one inference may carry, all sources together: each is executed on every demonstration."""
MAX_PRIOR_SOURCES = 8
MAX_SOURCE_NAME_CHARS = 200


class PriorSource(StrictBody):
    """Rules learned elsewhere (another service's stored set or inference): one vote among the priors."""

    source: str = Field(min_length=1, max_length=MAX_SOURCE_NAME_CHARS,
                        description="Where the rules come from, as the transferred rules name it (`ps_...@n`, a "
                        "request id, a file name).")
    rules: Preconditions = Field(description="Action (`Class.method`) → rules, as an inference's `preconditions`.")


class InferOptions(StrictBody):
    generators: list[Generator] = Field(
        default=["model", "enumerate"],
        min_length=1,
        max_length=2,
        description="Candidate generators. The default scores best on the dev numbers (docs/results.md); "
        "['enumerate'] alone is the model-free fast path (about a second; SGD F1 0.899 against 0.913).",
    )
    ranking: Ranking = Field(
        default="cautious",
        description="'cautious' (default): the conditions made true or renewed since the agent's previous turn "
        "(a disjunction of them when no single one covers the calls), plus, for tool calls, every positive fact "
        "that held at every call, kept as `assumed` because nothing shows the call can happen without it (safest "
        "in the states the demonstrations never show: docs/results.md, counterfactual table). The paper's "
        "criteria: 'subsumption' (eq. hopt); 'recency' keeps argument conditions and conditions made true since "
        "the agent's previous turn; 'marginal' keeps conditions while they still exclude enough points.",
    )
    unseen: Unseen = Field(
        default="refuse",
        description="What an action that no demonstration calls gets when nothing else decides it. Its rule is "
        "a prior rule (`prior_rules`, `prior_sets`) where one applies, else the code model's zero-shot guess where "
        "several samples agree (`decided: 'zero-shot'`), whichever value this has; only without either: "
        "'refuse' (default): the rule `False`, every call refused until a rule is written or learned; 'allow': "
        "no rule, every call allowed. Either way `warnings` names the action, and every `/check-actions` verdict "
        "on it says so (`rule_status`: 'transferred', 'zero-shot' or 'missing').",
    )
    now: str | None = Field(
        default=None, pattern=r"^\d{4}-\d{2}-\d{2}(T\d{2}:\d{2}(:\d{2})?)?$",
        description="The conversations' date and time (ISO, as the results write theirs), e.g. "
        "'2024-05-15T15:00:00': the enumerator then compares the results' dates with it (within a day before it; "
        "every segment's date not before its day). None: no condition on time.",
    )
    model_for: ModelFor = Field(
        default="thin",
        description="Which actions the code model proposes rules for: 'thin' (default): those demonstrated fewer "
        "than 3 times or in fewer than 3 demonstrations, where the evidence cannot decide and the model's reading "
        "of the spec is what is left, while the enumerator covers the others (without it, every action); 'all': "
        "every action (the paper). On every dev domain both give the same rules (docs/results.md), and 'thin' "
        "samples a fraction of the prompts (generation is most of the time).",
    )
    show_rules: bool = Field(
        default=True,
        description="With model_for 'thin': before the model proposes for a thinly or never demonstrated action, "
        "the prompt shows the rules the evidence settled for the other actions of its class (a success notice's "
        "`assert self.query_success` before the failure notice it is asked about), as code. On the dev domains "
        "this turns the 0.5B model's `assert False` for a never-demonstrated failure notice into "
        "`not self.query_success` (docs/results.md). False: each action's prompt alone (the paper).",
    )
    candidates: Listed = Field(
        default="kept",
        description="Which candidate reports the answer lists: 'kept' (default: the kept rules' reports only; with "
        "`evidence`, what a reviewer reads), 'all' (every candidate with why it was kept or dropped, the "
        "alternatives a reviewer may pick instead; hundreds of KB for a real domain), 'none'. The rules, warnings "
        "and evidence are the same either way.",
    )
    judge: bool = Field(
        default=False,
        description="Let the code model settle what the demonstrations cannot: a rule for an action never "
        "demonstrated, and whether a condition that only described the episode's phase is required. It scores "
        "the validated candidates (never adopts anything unexecuted) and decides only when confident.",
    )
    prior_rules: Preconditions = Field(
        default_factory=dict,
        description="Rules learned for other services (e.g. the `preconditions` of another inference or a stored "
        "set's rules): candidates, not verdicts. Each applies to the action of the same name, runs on these "
        "demonstrations like any candidate and is refuted when they contradict it; where they do not decide (an "
        "action never or thinly demonstrated, a correlate, an alternative reading of the same state) a prior "
        "that holds at every demonstrated call is preferred, and its rule says `decided: transferred`. A rule "
        "naming what this spec does not define is dropped (`warnings` says why). docs/method.md: 'Prior rules'.",
    )
    guarded: list[Annotated[str, StringConstraints(max_length=MAX_ACTION_CHARS)]] | None = Field(
        default=None, max_length=MAX_ACTIONS,
        description="The actions whose refusal protects something (`SYSTEM.BookFlight`, a state-changing tool, a "
        "confirmation): the cautious criterion keeps for them what it cannot rule out (assumed rules). The others "
        "are conversational acts (a goodbye, 'anything else?') and keep only what their calls establish; the "
        "assumed rules they did not keep are named in their warning. Default (null): from the spec, every action "
        "but those whose name says it opens, closes or keeps the conversation going (GOODBYE, HELLO, REQ_MORE, "
        "ANYTHING_ELSE, OUT_OF_SCOPE, THANK...); the warning says so. An action "
        "the spec does not define is a 422 naming it.",
    )
    library: bool = Field(
        default=True,
        description="Use the rule library shipped with the service as priors: the rules inferred on the "
        "development domains (20 dialog services and tasks), one source per domain, for a spec sharing at least "
        "three action names with one (`library:<domain>` names it in a transferred rule's `source`). Your own "
        "priors come on top: for an action they speak of, the library is silent. False: no library.",
    )
    prior_sets: list[Annotated[str, StringConstraints(pattern=SET_REFERENCE)]] = Field(
        default_factory=list, max_length=MAX_PRIOR_SOURCES,
        description="Your own stored precondition sets (`ps_...@n`, or `ps_...` for the latest) whose rules are "
        "priors, one vote each; resolved by the service before the job is queued (another tenant's set is a 404).",
    )
    prior_sources: list[PriorSource] = Field(
        default_factory=list, max_length=MAX_PRIOR_SOURCES,
        description="Priors from several sources, each one vote: where sources disagree on an action, the rules "
        "most of them name that the demonstrations do not refute are preferred. The service fills it from "
        "`prior_sets`.",
    )
    samples_per_prompt: int = Field(default=4, ge=1, le=64)
    prompts_per_action: int = Field(
        default=2, ge=1, le=MAX_DEMONSTRATIONS, description="How many demonstrations to vary across prompts."
    )
    demonstrations_per_prompt: int = Field(default=1, ge=1, le=10)
    temperature: float = Field(default=0.8, ge=0.0, le=2.0)
    top_p: float = Field(default=0.95, gt=0.0, le=1.0)
    max_new_tokens: int = Field(
        default=32, ge=4, le=256,
        description="Tokens per sampled assertion. 32 gives the default configuration the same rules as 48 on every "
        "dev domain (SGD and ALFWorld) with fewer decode steps: the longest samples are rambles that parse to nothing.",
    )
    seed: int = Field(default=0, ge=0, le=2**31 - 1)
    tolerance: float = Field(
        default=DEFAULT_TOLERANCE,
        ge=0.0,
        le=MAX_TOLERANCE,
        allow_inf_nan=False,
        description="Share of an action's demonstrated calls that may break a rule (agents' slips in real logs). "
        "0 is the paper's strict validation (a rule must hold at every occurrence; nothing else changes). Above "
        "0, a rule is kept when its exceptions are no more than slips at this rate explain, it holds at the "
        "occurrences clearly more often than at the other points of the same demonstrations, and the action "
        "occurs at least 3 times (fewer: treated as never demonstrated). "
        "docs/method.md: 'Evidence-weighted validation'.",
    )
    answer_slips: float = Field(
        default=DEFAULT_ANSWER_SLIPS,
        ge=0.0,
        le=MAX_TOLERANCE,
        allow_inf_nan=False,
        description="Share of an action's demonstrated calls at which a human agent may have reported the other "
        "answer (a 'reservation failed' notice after a success) while an answer came before every call. Within "
        "it, the test of the answer's value that the other calls share replaces the bare 'an answer came' "
        "(`self.query_success is not None`, which allows the notice after either answer); the calls it refuses "
        "are listed as the rule's exceptions in `evidence`. 0 keeps the bare test; ignored at `tolerance` 0 "
        "(strict validation). The default (0.3) is the evidence weighting's bound on slips (a minority of the "
        "calls), fixed before it was measured. docs/method.md: 'Evidence-weighted validation'.",
    )

    def priors(self) -> list[tuple[str, str, dict[str, list[str]]]]:
        """(source, the field that holds them, action -> rules) of every prior source of the request."""
        return [("options.prior_rules", "options.prior_rules", self.prior_rules)] + [
            (s.source, f"options.prior_sources[{k}].rules", s.rules) for k, s in enumerate(self.prior_sources)]

    @model_validator(mode="after")
    def _bounded_priors(self) -> InferOptions:
        total = sum(len(r) for r in self.prior_rules.values()) + sum(
            len(r) for s in self.prior_sources for r in s.rules.values())
        if total > MAX_PRIOR_RULES:
            raise ValueError(f"{total} prior rules (options.prior_rules and options.prior_sources together): at "
                             f"most {MAX_PRIOR_RULES}")
        if len(self.prior_sets) + len(self.prior_sources) > MAX_PRIOR_SOURCES:
            raise ValueError(f"more than {MAX_PRIOR_SOURCES} prior sources (options.prior_sets and "
                             "options.prior_sources together)")
        return self


SPEC_DESCRIPTION = (
    "The program spec: Python classes whose attributes summarise the history, observation methods, and "
        "action methods (a stub body, `pass`/`...`/docstring, marks an action whose rule is unknown). Parsed, "
        "never run, at the gateway; run only in the sandbox."
)
PRECONDITIONS_DESCRIPTION = (
    "Rules per action (`Class.method`): Python expressions over `self` and the action's parameters, written "
    "without `assert` (e.g. `self.user.informed_slot['city']`); a call is allowed when all hold. An action "
    "not named here has no rule."
)
HISTORY_DESCRIPTION = (
    "What happened so far: either a program over the spec (the statements creating the objects, then one call "
    "per step, e.g. `user = USER()`, `system = SYSTEM(user)`, `user.INFORM('city')`), or a list of events "
    "(`{\"actor\": \"user\", \"act\": \"INFORM\", \"args\": [\"city\"]}`) that the service renders to that "
    "program, arguments as literals only: what an end user typed can never become code. A dialog system should "
    "send events; a tool-calling LLM agent may send its OpenAI chat messages instead (over a spec from "
    "`precond convert openai`), rendered the same way."
)
MAX_HISTORY_EVENTS = 2_000
MAX_EVENT_ARGS = 32
PRECONDITION_SET_DESCRIPTION = (
    "A stored precondition set (`POST /precondition-sets`) to use instead of `spec` + `preconditions`: "
    "`id@version`, or `id` for its latest version. Another tenant's set is not found (404)."
)

Scalar = Annotated[
    Any,
    WithJsonSchema({"anyOf": [{"type": "string"}, {"type": "integer"}, {"type": "number"}, {"type": "boolean"},
                              {"type": "null"}]}),
]
"""An event argument: str, int, float, bool or null; anything else is refused (422) when the history is rendered."""


class HistoryEvent(BaseModel):
    """One step of a structured history: `actor.act(*args)`."""

    # Unknown fields are errors, as in StrictBody, whose guard runs once for all of a history's events
    # (_events_first_unknown_field_only); the docstring above is the API's description.
    model_config = ConfigDict(extra="forbid")

    actor: str = Field(max_length=100, description="The spec class's variable: its name in lower case (`user`, "
                       "`system`; `agent`, `environment`).")
    act: str = Field(max_length=MAX_ACTION_CHARS, description="A method of the actor's class (`INFORM`, `REQUEST`).")
    args: list[Scalar] = Field(
        default_factory=list, max_length=MAX_EVENT_ARGS,
        description="Positional arguments: strings, numbers, booleans or null only, rendered with `repr`.",
    )


ChatMessage = Annotated[
    dict[str, Any],
    WithJsonSchema({
        "type": "object",
        "description": "An OpenAI chat message: `{\"role\": \"user\", \"content\"}`, `{\"role\": \"assistant\", "
        "\"tool_calls\": [{\"function\": {\"name\", \"arguments\"}}]}`, `{\"role\": \"tool\", \"content\"}` "
        "(system messages are skipped). Checked and rendered by the service (docs/converting.md).",
        "properties": {"role": {"type": "string"}, "content": {}, "tool_calls": {"type": "array"},
                       "tool_call_id": {"type": "string"}, "name": {"type": "string"}},
        "required": ["role"],
    }),
]
"""A message of a tool-calling agent's log; its shape is checked when the history is rendered (422 naming it)."""


def _events_first_unknown_field_only(events: Any) -> Any:
    """`StrictBody`'s guard for each event, in one call for the whole history: called by pydantic for each event
    instead, it took most of the validation of a 40 events history (80-138 → 35 µs)."""
    if isinstance(events, list):
        return [_first_unknown_field_only(event, HistoryEvent.model_fields) for event in events]
    return events


def _history_kind(value: Any) -> str:
    if isinstance(value, str):
        return "text"
    first = value[0] if isinstance(value, list) and value else None
    return "openai" if isinstance(first, dict) and "role" in first else "events"


History = Annotated[
    Annotated[str, Tag("text"), Field(max_length=MAX_SOURCE_CHARS)]
    | Annotated[list[HistoryEvent], Field(max_length=MAX_HISTORY_EVENTS),
                BeforeValidator(_events_first_unknown_field_only), Tag("events")]
    | Annotated[list[ChatMessage], Tag("openai"), Field(max_length=MAX_HISTORY_EVENTS)],
    Discriminator(_history_kind),
]


class ToolCall(StrictBody):
    """A proposed tool call, as an LLM agent writes it; rendered to `agent.<name>(...)` over a spec that
    `precond convert openai` made (its parameters in the stub's order)."""

    name: str = Field(max_length=MAX_ACTION_CHARS, description="The tool (a stub of the spec's AGENT).")
    arguments: str | dict[str, Any] = Field(
        default="{}", description="The arguments: a JSON object, or its text as OpenAI sends it.",
    )


class _UsesRules(StrictBody):
    """Rules come inline (`spec` + `preconditions`) or from a stored set (`precondition_set`), never both."""

    spec: str | None = Field(default=None, min_length=1, max_length=MAX_SOURCE_CHARS, description=SPEC_DESCRIPTION)
    precondition_set: str | None = Field(default=None, pattern=SET_REFERENCE,
                                         description=PRECONDITION_SET_DESCRIPTION)

    @model_validator(mode="after")
    def _one_source_of_rules(self) -> _UsesRules:
        if self.precondition_set is None and self.spec is None:
            raise ValueError("give `spec` (with `preconditions`) or `precondition_set`")
        if self.precondition_set is not None and (self.spec is not None or getattr(self, "preconditions", None)):
            raise ValueError("`precondition_set` replaces `spec` and `preconditions`: give one or the other")
        return self

    def spec_text(self) -> str:
        """The spec; a request naming a stored set has it filled in by the gateway before it is queued."""
        if self.spec is None:
            raise ValueError("precondition_set must be resolved by the service before the request runs")
        return self.spec


MAX_COUNTEREXAMPLE_RUNS = 200
MAX_LABELLED_CALLS = 64
CallVerdictLabel = Literal["refuse", "allow"]


class LabelledCall(StrictBody):
    """One call of a run that the rules must refuse (or must allow), after the lines before it."""

    line: int = Field(ge=1, description="1-based line of the call in the run's program; the lines before it are its "
                      "history.")
    verdict: CallVerdictLabel = Field(description="'refuse': the call breaks the policy (an incident, a review, a "
                                      "label); 'allow': it keeps it.")
    name: str | None = Field(default=None, max_length=MAX_SOURCE_NAME_CHARS,
                             description="Where the label comes from (`labels.json[12]`), quoted in reports.")


class Counterexamples(StrictBody):
    """Labelled calls of one run: a run of its own (`program`) or one of the demonstrations (`demonstration`),
    where a call labelled 'refuse' is evidence against a rule that allows it, not for one."""

    program: str | None = Field(default=None, min_length=1, max_length=MAX_SOURCE_CHARS,
                                description="A run over the spec that is not a demonstration (a failed run).")
    demonstration: int | None = Field(default=None, ge=0, description="Index of a demonstration instead.")
    calls: list[LabelledCall] = Field(min_length=1, max_length=MAX_LABELLED_CALLS)

    @model_validator(mode="after")
    def _one_run(self) -> Counterexamples:
        if (self.program is None) == (self.demonstration is None):
            raise ValueError("give `program` or `demonstration`, one of them")
        return self


class InferRequest(StrictBody):
    spec: str = Field(min_length=1, max_length=MAX_SOURCE_CHARS, description=SPEC_DESCRIPTION)
    demonstrations: list[str] = Field(
        min_length=1,
        max_length=MAX_DEMONSTRATIONS,
        description="Demonstration trajectories, each a program over the spec. At least one must call one of "
        "the actions: the rules are learned from the states in which they are called (422 otherwise).",
    )
    actions: list[str] | None = Field(
        default=None,
        max_length=256,
        description="Actions (`Class.method`) to infer rules for; default: every stub method of the spec.",
    )
    options: InferOptions = Field(default_factory=InferOptions, description="How candidates are made and ranked.")
    counterexamples: list[Counterexamples] = Field(
        default_factory=list, max_length=MAX_COUNTEREXAMPLE_RUNS,
        description="Labelled calls (`precond convert openai --labels`, a review, or by hand): each rule of an "
        "action with such calls is chosen to refuse the calls labelled 'refuse' and allow the demonstrated calls "
        "and those labelled 'allow' (docs/api.md: 'Counterexamples'). Never shown to the code model.",
    )


class RuleException(StrictBody):
    """A demonstrated call at which a rule does not hold: a slip in the log, or a sign the rule is wrong."""

    demonstration: int = Field(description="Index of the demonstration.")
    position: int = Field(description="The step: index of the statement in the demonstration's main body.")
    line: int | None = Field(default=None, description="Line of that call in the demonstration.")
    call: str | None = Field(default=None, description="The demonstrated call, as written.")


Verdict = Literal["held", "tolerated", "refuted", "chance", "thin"]


class RuleEvidence(StrictBody):
    """What the demonstrations say about one rule (docs/method.md: 'Evidence-weighted validation')."""

    occurrences: int = Field(description="Demonstrated calls of the action.")
    holds: int = Field(description="How many of them the rule allows.")
    exceptions: list[RuleException] = Field(
        default_factory=list,
        description=f"The calls it refuses (listed for rules that passed validation, at most "
        f"{MAX_LISTED_EXCEPTIONS}); `occurrences - holds` counts them all.",
    )
    elsewhere: int = Field(default=0, description="Other points of the same demonstrations (positions x arguments).")
    holds_elsewhere: int = Field(default=0, description="How many of those it holds at.")
    confidence: float = Field(
        description="Lower 95% bound on the share of the action's calls the rule allows (Wilson): 1 of 1 gives "
        "0.27, 40 of 40 gives 0.94."
    )
    verdict: Verdict = Field(
        description="'held' at every occurrence, 'tolerated' (exceptions within `options.tolerance`), 'refuted' "
        "(too many exceptions), 'chance' (holds about as often elsewhere: says nothing), 'thin' (too few "
        "occurrences to learn from)."
    )
    decided: Decided | None = Field(
        default=None,
        description="For a kept rule, how it was decided: 'established' (the evidence decides: it enabled the "
        "demonstrated calls), 'assumed' (kept because it could not be ruled out: a fact that held at every call "
        "but may be a correlate; review it), 'zero-shot' (the code model's guess, no evidence), 'unseen' (the "
        "action was never demonstrated and `options.unseen` is 'refuse'), 'transferred' (a prior rule, "
        "`options.prior_rules` or `prior_sets`, that the demonstrations did not refute and could not decide "
        "against: `source` says where it was learned).",
    )
    source: str | None = Field(
        default=None, max_length=4 * MAX_SOURCE_NAME_CHARS,
        description="For a transferred rule: the prior sources that name it (`ps_...@n`, `options.prior_rules`).",
    )
    refuses: list[str] = Field(
        default_factory=list,
        description="The labelled calls (`counterexamples`) to refuse that this rule refuses, by name.",
    )
    refuses_allowed: list[str] = Field(
        default_factory=list,
        description="The calls labelled 'allow' (or demonstrated and not labelled) that this rule refuses: where "
        "it disagrees with the labels.",
    )


class CandidateReport(StrictBody):
    assertion: str
    source: Literal["model", "enumerate", "prior"]
    valid: bool = Field(description="Passed validation: held at every occurrence, or within `options.tolerance`.")
    cluster: int | None = None
    support: int = Field(description="|C_h|: demonstration points (position x arguments) where it holds.")
    kept: bool
    reason: str | None = Field(
        default=None,
        description="Why it was kept or dropped, in words: 'violated at demonstrations[3], line 12, ...', 'subsumed "
        "by ...', 'held at every occurrence, but was already true before the user's last turn: looks like a "
        "phase, not a requirement', 'zero-shot: never demonstrated, kept by model vote', 'kept: ...'. Set for "
        "every candidate the engine reports.",
    )
    evidence: RuleEvidence | None = Field(default=None, description="Its counts; absent for rejected candidates.")


class StageCounts(StrictBody):
    sampled: int = 0
    parsed: int = 0
    valid: int = 0
    clusters: int = 0
    kept: int = 0


class InferStats(StrictBody):
    actions: dict[str, StageCounts]
    total: StageCounts
    seconds: dict[str, float] = Field(description="Wall time per phase: trace, generate, validate, rank.")


class ModelInfo(StrictBody):
    name: str
    sha256: str | None = None
    device: str
    dtype: str
    dtype_reason: str = Field(
        default="",
        description="Why the model runs in `dtype`: the setting, or what the device can do "
        "(e.g. 'cpu without avx512_bf16/amx_bf16: float32').",
    )
    quant: str = Field(
        default="none",
        description="How the weights are stored: `none` (in `dtype`) or `int8` (linear layers and embedding in 8 bits, "
        "`MODEL_QUANT`).",
    )
    quant_reason: str = Field(
        default="", description="Why: the setting, or what the CPU can do (e.g. 'int8 weights: cpu with avx512_vnni')."
    )
    adapter: str | None = Field(
        default=None,
        description="The trained policy the model predicts with (`precond train-policy`): its name and the first "
        "12 hex digits of its weights' sha256; null for the base model.",
    )


class InferResponse(StrictBody):
    preconditions: dict[str, list[str]]
    program: str
    candidates: dict[str, list[CandidateReport]]
    stats: InferStats
    model: ModelInfo | None = Field(default=None, description="None when no generator used a model.")
    warnings: dict[str, str] = Field(
        default_factory=dict,
        description="Per action whose rule is empty (every call allowed) or not backed by enough demonstrated "
        "calls, why: `no occurrence` (no demonstration calls it), `thin evidence` (fewer than 3 calls in 3 "
        "demonstrations) or `empty rule` (no candidate passed validation). Absent: a rule learned from evidence. "
        "Also per demonstration left out (`demonstrations[12]`): one that hits a sandbox limit (time, memory, "
        "size) even when run alone teaches nothing, and the warning names the limit and the setting to raise.",
    )
    evidence: dict[str, dict[str, RuleEvidence]] = Field(
        default_factory=dict,
        description="Per action, per kept rule: its evidence (occurrences, holds, exceptions, confidence), to "
        "store with the rules and to decide whether the log or the rule is wrong.",
    )


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


JobKind = Literal["infer", "next-action", "check", "validate", "reinfer", "train-policy"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class ErrorInfo(StrictBody):
    type: str
    message: str
    field: str | None = None
    blocked: list[Blocked] | None = Field(
        default=None, description="`blocks_demonstration`: every demonstrated call the new rules would refuse (the "
        "rule and where), so that a reviewer sees which demonstrations it blocks. The ways out: `force: true` "
        "(they become the rule's known exceptions), a `reject` edit of the rule (or the set stored without it), "
        "or the demonstrations left out.")


class ErrorResponse(StrictBody):
    error: ErrorInfo
    request_id: str


class JobProgress(StrictBody):
    phase: str = "queued"
    done: int = 0
    total: int = 0


class JobStatus(StrictBody):
    id: str
    kind: JobKind
    status: JobState
    progress: JobProgress = Field(default_factory=JobProgress)
    result: dict[str, Any] | None = None
    error: ErrorInfo | None = None
    wait_max_s: float | None = Field(
        default=None,
        description="In a POST's 202 only: the longest the server waits for a job before answering 202 "
        "(`PRECOND_WAIT_MAX_S`); a `?wait=` above it was cut to it. The job runs on: poll `Location`.",
    )

