"""Guarded actions and conversational acts: the cost of a wrong verdict is not the same for every action.

A guarded action protects something: a service call that books or pays, a state-changing tool, a confirmation
that commits the user. Allowing one where its requirement fails is the harm a guard exists for, so the cautious
criterion keeps what it cannot rule out (assumed rules). A conversational act (a goodbye, "anything else?", an
out-of-scope reply) protects nothing: refusing it where a correlate fails leaves the user at a dead end, so it
keeps only the rules its calls establish (`cautious.choose`), and never the bare answer of the agent's own service
call (a goodbye after a success or after a failure). The follow-up offer ("anything else?", `FOLLOW_UP`) keeps
that some answer came: it is asked once a request was served, after a success or a failure alike.

`options.guarded` names the guarded actions; without it they come from the spec (`default`): every action but
those whose name says it opens, closes or keeps the conversation going. Every answer that used the default says
so in the warnings of the conversational acts it changed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from precond.programs import Method, checks

SMALL_TALK = ("GOODBYE", "BYE", "HELLO", "GREET", "THANK", "WELCOME", "ANYTHING_ELSE", "REQ_MORE", "OUT_OF_SCOPE")
"""Words of the conversational acts' names: opening, closing, "anything else?", "I cannot help with that"."""


FOLLOW_UP = ("ANYTHING_ELSE", "REQ_MORE")
"""Words of the follow-up offer's name ("anything else?"): asked once the agent served a request, so it keeps that
an answer came (`cautious.choose`), whatever the answer was."""


UNREFUSED = ("conversational act (not in options.guarded): never refused for want of a rule, whatever options.unseen "
             "says")


def method_name(action: str) -> str:
    return action.rsplit(".", 1)[-1]


def conversational_name(name: str) -> bool:
    """A dialog act that opens, closes or keeps the conversation going (`GOODBYE`, `REQ_MORE`, `OUT_OF_SCOPE`)."""
    upper = name.upper()
    return any(word in upper for word in SMALL_TALK)


def follow_up_name(name: str) -> bool:
    """A conversational act that offers more help (`ANYTHING_ELSE`, `REQ_MORE`)."""
    upper = name.upper()
    return any(word in upper for word in FOLLOW_UP)


def default(actions: Sequence[str]) -> list[str]:
    """Every action but the conversational acts: service calls (`FindBus`), tools (`take`), confirmations, notices,
    and dialog acts that change state (`BLOCK_CARD`)."""
    return [a for a in actions if not conversational_name(method_name(a))]


def resolve(requested: Sequence[str] | None, actions: Sequence[str], methods: Mapping[str, Method]) -> list[str]:
    """The request's guarded actions (each one the spec defines, else the 422 naming it), or the default."""
    if requested is None:
        return default(actions)
    for index, name in enumerate(requested):
        if name not in methods:
            raise checks.unknown_action(name, methods, f"options.guarded[{index}]")
    return list(requested)


def note(guarded: Sequence[str]) -> str:
    shown = ", ".join(method_name(a) for a in guarded) or "none"
    return (f"options.guarded not given: its default from the spec guards every action but the conversational "
            f"acts (greetings, goodbyes, 'anything else?', out of scope): {shown}")
