"""`POST /infer`: its options (prior sets included), the counterexamples it may be given, its answer."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, StringConstraints, model_validator

from precond_client.schemas.common import (
    DEFAULT_ANSWER_SLIPS,
    DEFAULT_TOLERANCE,
    MAX_ACTION_CHARS,
    MAX_ACTIONS,
    MAX_DEMONSTRATIONS,
    MAX_LISTED_EXCEPTIONS,
    MAX_SOURCE_CHARS,
    MAX_TOLERANCE,
    SET_REFERENCE,
    SPEC_DESCRIPTION,
    Decided,
    Generator,
    Listed,
    ModelFor,
    Preconditions,
    Ranking,
    StrictBody,
    Unseen,
)

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
