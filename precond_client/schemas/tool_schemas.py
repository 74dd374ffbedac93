"""A proposed tool call checked against its tool's JSON Schema (the `parameters` of its OpenAI tool schema).

`precond convert openai` keeps each tool's schema in the spec it writes (`SCHEMAS = {tool: parameters}`, after
`WRITES`: `openai_log.read_schemas`), so that the embedded guard (`guard.Guard`) and the service (`engine.check`)
read the same schemas from the same text, and refuse a call whose arguments break its schema (`"amount": "29.99"`
where the schema says number) with the schema's own reason, before any rule is asked. The check is `jsonschema`'s,
under the draft the schema names (2020-12 when it names none). The keywords whose regular expressions would run in
the caller's process on the caller's text (`pattern`, `patternProperties`) are not checked: a spec is untrusted,
and a regular expression can take exponential time outside the sandbox's limits. A schema that is not valid, or
that refers to a schema it does not hold, refuses every call of its tool with that reason (fail closed).
"""

from __future__ import annotations

import json
from functools import lru_cache
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from jsonschema.protocols import Validator

UNCHECKED = ("pattern", "patternProperties")
SCHEMA_BROKEN = "arguments break"
"""How a refusal for the schema starts (`guard.refusal` tells the model to fix the arguments)."""
MESSAGE_CHARS = 300


def schema_error(schema: dict[str, Any]) -> str | None:
    """Why `schema` is not a JSON Schema the check can use (None: it is one)."""
    try:
        _validator(json.dumps(schema, sort_keys=True))
    except Exception as exc:  # whatever jsonschema or json raise for it, said
        return _clean(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    return None


def schema_problem(tool: str, schema: dict[str, Any] | None, arguments: Any) -> str | None:
    """Why `arguments` (the call's JSON object, as sent) break the tool's schema, in the schema's words and at
    the argument's path; None when they keep it, or when the tool has no schema."""
    if schema is None:
        return None
    from jsonschema import exceptions  # imported on the first call with a schema: `import precond_client` stays light

    try:
        checker = _validator(json.dumps(schema, sort_keys=True))
        if _plainly_kept(schema, arguments):
            return None
        error = exceptions.best_match(checker.iter_errors(arguments))
    except Exception as exc:  # not a schema, a reference it does not hold, ...: the call is refused (fail closed)
        return f"{tool}'s JSON Schema cannot be checked: {_clean(str(exc).splitlines()[0] if str(exc) else exc)}"
    if error is None:
        return None
    where = "/".join(str(p) for p in error.absolute_path) or "arguments"
    return f"{SCHEMA_BROKEN} {tool}'s JSON Schema: {where}: {_clean(error.message)}"


@lru_cache(maxsize=256)
def _validator(schema_text: str) -> Validator:
    """A checked validator of the schema (SchemaError when it is not a schema), without `UNCHECKED`."""
    from jsonschema import validators

    schema = json.loads(schema_text)
    cls = validators.validator_for(schema, default=validators.Draft202012Validator)
    cls.check_schema(schema)
    unchecked = validators.extend(cls, {keyword: None for keyword in UNCHECKED})
    return unchecked(schema)


PLAIN = frozenset({"type", "properties", "required", "items", "enum", "description", "title"})
"""The keywords `_plainly_kept` reads (what tool schemas mostly hold); a schema with any other goes to jsonschema."""
_PLAIN_TYPES = {"string": (str,), "boolean": (bool,), "integer": (int,), "number": (int, float), "array": (list,),
                "object": (dict,), "null": (type(None),)}


def _plainly_kept(schema: Any, value: Any) -> bool:
    """True only where `value` surely keeps `schema` (as jsonschema would say) by the `PLAIN` keywords alone: the
    common call is then not walked by jsonschema's validator (most of a guard's check). False is "not sure": the
    caller asks jsonschema, whose words a refusal says. Types are matched exactly (`type(value)`, no bool for an
    integer, no float for one), enums only for text, so that it never says kept where jsonschema says broken."""
    if not isinstance(schema, dict) or not PLAIN.issuperset(schema):
        return False
    kind = schema.get("type")
    if kind is not None and (not isinstance(kind, str) or type(value) not in _PLAIN_TYPES.get(kind, ())):
        return False
    if "enum" in schema and not (type(value) is str and isinstance(schema["enum"], list)
                                 and any(type(e) is str and e == value for e in schema["enum"])):
        return False
    if type(value) is dict:
        required, properties = schema.get("required", []), schema.get("properties", {})
        if not isinstance(required, list) or not isinstance(properties, dict) or any(r not in value for r in required):
            return False
        if not all(_plainly_kept(properties[k], v) for k, v in value.items() if k in properties):
            return False
    if type(value) is list and "items" in schema:
        return all(_plainly_kept(schema["items"], v) for v in value)
    return True


def _clean(text: object) -> str:
    said = " ".join(str(text).split())
    return said if len(said) <= MESSAGE_CHARS else said[: MESSAGE_CHARS - 3] + "..."
