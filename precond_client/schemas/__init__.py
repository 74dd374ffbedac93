"""Request/response bodies shared by the CLI, the gateway, the worker and the engine (one place, one truth),
one module per resource; every name is re-exported here, so `from precond_client.schemas import X` reads
any of them.

They live here, not in `precond/gateway/` or `precond/worker/`, because the CLI, the gateway, the queue
payloads and the engine all speak them: a field renamed in one place must fail everywhere at once.
Size bounds are part of the contract: they turn hostile inputs into 422s before any work is queued.
"""

from __future__ import annotations

from precond_client.schemas.calls import (
    HISTORY_DESCRIPTION as HISTORY_DESCRIPTION,
)
from precond_client.schemas.calls import (
    MAX_EVENT_ARGS as MAX_EVENT_ARGS,
)
from precond_client.schemas.calls import (
    MAX_HISTORY_EVENTS as MAX_HISTORY_EVENTS,
)
from precond_client.schemas.calls import (
    PRECONDITION_SET_DESCRIPTION as PRECONDITION_SET_DESCRIPTION,
)
from precond_client.schemas.calls import (
    PRECONDITIONS_DESCRIPTION as PRECONDITIONS_DESCRIPTION,
)
from precond_client.schemas.calls import (
    ChatMessage as ChatMessage,
)
from precond_client.schemas.calls import (
    History as History,
)
from precond_client.schemas.calls import (
    HistoryEvent as HistoryEvent,
)
from precond_client.schemas.calls import (
    Scalar as Scalar,
)
from precond_client.schemas.calls import (
    ToolCall as ToolCall,
)
from precond_client.schemas.check import (
    Blocked as Blocked,
)
from precond_client.schemas.check import (
    CallVerdict as CallVerdict,
)
from precond_client.schemas.check import (
    CheckRequest as CheckRequest,
)
from precond_client.schemas.check import (
    CheckResponse as CheckResponse,
)
from precond_client.schemas.check import (
    ValidateResponse as ValidateResponse,
)
from precond_client.schemas.common import (
    ADAPTER_ID_PATTERN as ADAPTER_ID_PATTERN,
)
from precond_client.schemas.common import (
    ADAPTER_REFERENCE as ADAPTER_REFERENCE,
)
from precond_client.schemas.common import (
    DEFAULT_ANSWER_SLIPS as DEFAULT_ANSWER_SLIPS,
)
from precond_client.schemas.common import (
    DEFAULT_TOLERANCE as DEFAULT_TOLERANCE,
)
from precond_client.schemas.common import (
    MAX_ACTION_CHARS as MAX_ACTION_CHARS,
)
from precond_client.schemas.common import (
    MAX_ACTIONS as MAX_ACTIONS,
)
from precond_client.schemas.common import (
    MAX_ASSERTION_CHARS as MAX_ASSERTION_CHARS,
)
from precond_client.schemas.common import (
    MAX_ASSERTIONS_PER_ACTION as MAX_ASSERTIONS_PER_ACTION,
)
from precond_client.schemas.common import (
    MAX_CALL_CHARS as MAX_CALL_CHARS,
)
from precond_client.schemas.common import (
    MAX_CALLS as MAX_CALLS,
)
from precond_client.schemas.common import (
    MAX_DEMONSTRATIONS as MAX_DEMONSTRATIONS,
)
from precond_client.schemas.common import (
    MAX_LISTED_EXCEPTIONS as MAX_LISTED_EXCEPTIONS,
)
from precond_client.schemas.common import (
    MAX_SOURCE_CHARS as MAX_SOURCE_CHARS,
)
from precond_client.schemas.common import (
    MAX_THOUGHT_CHARS as MAX_THOUGHT_CHARS,
)
from precond_client.schemas.common import (
    MAX_TOLERANCE as MAX_TOLERANCE,
)
from precond_client.schemas.common import (
    POLICY_PATTERN as POLICY_PATTERN,
)
from precond_client.schemas.common import (
    SET_REFERENCE as SET_REFERENCE,
)
from precond_client.schemas.common import (
    SPEC_DESCRIPTION as SPEC_DESCRIPTION,
)
from precond_client.schemas.common import (
    Assertion as Assertion,
)
from precond_client.schemas.common import (
    Decided as Decided,
)
from precond_client.schemas.common import (
    Generator as Generator,
)
from precond_client.schemas.common import (
    JudgedBy as JudgedBy,
)
from precond_client.schemas.common import (
    Listed as Listed,
)
from precond_client.schemas.common import (
    ModelFor as ModelFor,
)
from precond_client.schemas.common import (
    Preconditions as Preconditions,
)
from precond_client.schemas.common import (
    Ranking as Ranking,
)
from precond_client.schemas.common import (
    SourceText as SourceText,
)
from precond_client.schemas.common import (
    StrictBody as StrictBody,
)
from precond_client.schemas.common import (
    Unseen as Unseen,
)
from precond_client.schemas.infer import (
    MAX_COUNTEREXAMPLE_RUNS as MAX_COUNTEREXAMPLE_RUNS,
)
from precond_client.schemas.infer import (
    MAX_LABELLED_CALLS as MAX_LABELLED_CALLS,
)
from precond_client.schemas.infer import (
    MAX_PRIOR_RULES as MAX_PRIOR_RULES,
)
from precond_client.schemas.infer import (
    MAX_PRIOR_SOURCES as MAX_PRIOR_SOURCES,
)
from precond_client.schemas.infer import (
    MAX_SOURCE_NAME_CHARS as MAX_SOURCE_NAME_CHARS,
)
from precond_client.schemas.infer import (
    CallVerdictLabel as CallVerdictLabel,
)
from precond_client.schemas.infer import (
    CandidateReport as CandidateReport,
)
from precond_client.schemas.infer import (
    Counterexamples as Counterexamples,
)
from precond_client.schemas.infer import (
    InferOptions as InferOptions,
)
from precond_client.schemas.infer import (
    InferRequest as InferRequest,
)
from precond_client.schemas.infer import (
    InferResponse as InferResponse,
)
from precond_client.schemas.infer import (
    InferStats as InferStats,
)
from precond_client.schemas.infer import (
    LabelledCall as LabelledCall,
)
from precond_client.schemas.infer import (
    ModelInfo as ModelInfo,
)
from precond_client.schemas.infer import (
    PriorSource as PriorSource,
)
from precond_client.schemas.infer import (
    RuleEvidence as RuleEvidence,
)
from precond_client.schemas.infer import (
    RuleException as RuleException,
)
from precond_client.schemas.infer import (
    StageCounts as StageCounts,
)
from precond_client.schemas.infer import (
    Verdict as Verdict,
)
from precond_client.schemas.jobs import (
    ErrorInfo as ErrorInfo,
)
from precond_client.schemas.jobs import (
    ErrorResponse as ErrorResponse,
)
from precond_client.schemas.jobs import (
    JobKind as JobKind,
)
from precond_client.schemas.jobs import (
    JobProgress as JobProgress,
)
from precond_client.schemas.jobs import (
    JobState as JobState,
)
from precond_client.schemas.jobs import (
    JobStatus as JobStatus,
)
from precond_client.schemas.next_action import (
    DECIDED_DESCRIPTION as DECIDED_DESCRIPTION,
)
from precond_client.schemas.next_action import (
    RULE_STATUS_DESCRIPTION as RULE_STATUS_DESCRIPTION,
)
from precond_client.schemas.next_action import (
    STATUS_OF_DECIDED as STATUS_OF_DECIDED,
)
from precond_client.schemas.next_action import (
    WEAKEST_FIRST as WEAKEST_FIRST,
)
from precond_client.schemas.next_action import (
    AllowedCall as AllowedCall,
)
from precond_client.schemas.next_action import (
    ChooseBy as ChooseBy,
)
from precond_client.schemas.next_action import (
    Decisions as Decisions,
)
from precond_client.schemas.next_action import (
    NextActionMode as NextActionMode,
)
from precond_client.schemas.next_action import (
    NextActionOptions as NextActionOptions,
)
from precond_client.schemas.next_action import (
    NextActionRequest as NextActionRequest,
)
from precond_client.schemas.next_action import (
    NextActionResponse as NextActionResponse,
)
from precond_client.schemas.next_action import (
    PredictedAction as PredictedAction,
)
from precond_client.schemas.next_action import (
    Rejection as Rejection,
)
from precond_client.schemas.next_action import (
    RuleStatus as RuleStatus,
)
from precond_client.schemas.next_action import (
    rule_status as rule_status,
)
from precond_client.schemas.sets import (
    CANDIDATES_DESCRIPTION as CANDIDATES_DESCRIPTION,
)
from precond_client.schemas.sets import (
    EVIDENCE_DESCRIPTION as EVIDENCE_DESCRIPTION,
)
from precond_client.schemas.sets import (
    MAX_REPORTED_CANDIDATES as MAX_REPORTED_CANDIDATES,
)
from precond_client.schemas.sets import (
    MAX_SET_EDITS as MAX_SET_EDITS,
)
from precond_client.schemas.sets import (
    WARNINGS_DESCRIPTION as WARNINGS_DESCRIPTION,
)
from precond_client.schemas.sets import (
    Candidates as Candidates,
)
from precond_client.schemas.sets import (
    EditOp as EditOp,
)
from precond_client.schemas.sets import (
    Evidence as Evidence,
)
from precond_client.schemas.sets import (
    PreconditionSet as PreconditionSet,
)
from precond_client.schemas.sets import (
    PreconditionSetCreate as PreconditionSetCreate,
)
from precond_client.schemas.sets import (
    PreconditionSetEdit as PreconditionSetEdit,
)
from precond_client.schemas.sets import (
    PreconditionSetList as PreconditionSetList,
)
from precond_client.schemas.sets import (
    PreconditionSetReinfer as PreconditionSetReinfer,
)
from precond_client.schemas.sets import (
    PreconditionSetSummary as PreconditionSetSummary,
)
from precond_client.schemas.sets import (
    RuleChange as RuleChange,
)
from precond_client.schemas.sets import (
    RuleEdit as RuleEdit,
)
from precond_client.schemas.sets import (
    SetCounterexample as SetCounterexample,
)
from precond_client.schemas.sets import (
    SetDiff as SetDiff,
)
