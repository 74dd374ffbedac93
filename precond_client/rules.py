"""Edits of a stored precondition set, typed: `client.edit_set(set_id, [require("SYSTEM.INFORM", rule)])`."""

from __future__ import annotations

from precond_client.schemas import RuleEdit


def add(action: str, rule: str) -> RuleEdit:
    """Add a rule (checked against the set's demonstrations: refused if it blocks one, unless forced)."""
    return RuleEdit(op="add", action=action, rule=rule)


def remove(action: str, rule: str) -> RuleEdit:
    """Remove a rule (re-inference may bring it back; `reject` keeps it out)."""
    return RuleEdit(op="remove", action=action, rule=rule)


def require(action: str, rule: str) -> RuleEdit:
    """Mark a rule required: every re-inference keeps it."""
    return RuleEdit(op="require", action=action, rule=rule)


def reject(action: str, rule: str) -> RuleEdit:
    """Remove a rule and mark it rejected: re-inference never brings it back."""
    return RuleEdit(op="reject", action=action, rule=rule)
