"""The bounds, literals and base body every resource's schemas share: the size bounds that turn hostile
inputs into 422s before any work is queued, `StrictBody`, and a set's rules (`Preconditions`)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

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
SPEC_DESCRIPTION = (
    "The program spec: Python classes whose attributes summarise the history, observation methods, and "
        "action methods (a stub body, `pass`/`...`/docstring, marks an action whose rule is unknown). Parsed, "
        "never run, at the gateway; run only in the sandbox."
)
