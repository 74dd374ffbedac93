"""What the operations that judge an agent's calls share: the history, a tool call, the rules they use."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, BeforeValidator, ConfigDict, Discriminator, Field, Tag, WithJsonSchema, model_validator

from precond_client.schemas.common import (
    MAX_ACTION_CHARS,
    MAX_SOURCE_CHARS,
    SET_REFERENCE,
    SPEC_DESCRIPTION,
    StrictBody,
    _first_unknown_field_only,
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
