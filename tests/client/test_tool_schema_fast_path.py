"""The plain-keyword path of the schema check (`tool_schemas._plainly_kept`) never says a call keeps a schema that
jsonschema says it breaks, so that a refusal for the schema is the same with it as without; and it does take the
common call (a plain object of text, numbers and lists) without jsonschema."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from jsonschema import Draft202012Validator

from precond_client.schemas.tool_schemas import _plainly_kept, schema_problem

TYPES = ("string", "boolean", "integer", "number", "array", "object", "null")
leaf = st.one_of(st.none(), st.booleans(), st.integers(-3, 3), st.floats(allow_nan=False), st.text(max_size=3),
                 st.sampled_from(["a", "b", 1.0, 0, True]))
values = st.recursive(leaf, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                    st.dictionaries(st.sampled_from(["a", "b", "c"]), inner,
                                                                    max_size=3)), max_leaves=8)


def _schemas(inner: st.SearchStrategy[Any]) -> st.SearchStrategy[dict[str, Any]]:
    return st.fixed_dictionaries({}, optional={
        "type": st.sampled_from(TYPES), "description": st.text(max_size=3),
        "enum": st.lists(st.sampled_from(["a", "b", 0, 1, True, False, 1.0, None]), min_size=1, max_size=3),
        "required": st.lists(st.sampled_from(["a", "b", "c"]), unique=True, max_size=2),
        "properties": st.dictionaries(st.sampled_from(["a", "b", "c"]), inner, max_size=3),
        "items": inner, "additionalProperties": st.booleans(), "minimum": st.integers(-1, 1)})


schemas = st.recursive(_schemas(st.just({})), _schemas, max_leaves=6)


def test_the_plain_path_says_kept_only_where_jsonschema_does(examples: Callable[[int], int]) -> None:
    @settings(max_examples=examples(2000), deadline=None)
    @given(schemas, values)
    def kept_only_where_jsonschema_keeps(schema: dict[str, Any], value: Any) -> None:
        if _plainly_kept(schema, value):
            assert Draft202012Validator(schema).is_valid(value)

    kept_only_where_jsonschema_keeps()


def test_a_plain_call_is_kept_without_jsonschema_and_a_broken_one_still_gets_its_reason() -> None:
    schema = {"type": "object", "required": ["order_id", "item_ids"], "properties": {
        "order_id": {"type": "string", "description": "The order."}, "item_ids": {"type": "array", "items": {
            "type": "string"}}, "reason": {"type": "string", "enum": ["no longer needed", "ordered by mistake"]}}}
    kept = {"order_id": "#W1", "item_ids": ["1", "2"], "reason": "no longer needed"}
    assert _plainly_kept(schema, kept) and schema_problem("t", schema, kept) is None
    assert not _plainly_kept(schema, {**kept, "reason": "bored"})
    assert schema_problem("t", schema, {**kept, "item_ids": ["1", 2]}) == \
        "arguments break t's JSON Schema: item_ids/1: 2 is not of type 'string'"
