"""An assumed rule of a tool call is about that call: what it names, what was read of it, or the user's words.

The cautious criterion keeps, as assumed, every positive fact that held at each demonstrated call of a tool call
(nothing shows the call without it). In a tool-calling agent's spec (`precond convert openai`) one such fact is
about no call at all: `self.last_ok`, whether the call right before succeeded, which every tool result
overwrites. As a rule it requires that whatever came last (a search, a scratch `think`, the write's own failed
first try) succeeded: a policy that needs a read names the read (`reservation_id in self.results[...]`), and a
write retried after an error is exactly what an agent must be able to do. So an assumed rule of a tool spec's
action stays only where it names one of the call's parameters or the user (`self.user`, what they said);
another is dropped, and says why. Established rules (made true right before the calls) and a rule the labels
chose are never touched: dropping a rule only allows more, so every demonstrated call stays allowed.
"""

from __future__ import annotations

import ast
from collections.abc import Sequence
from dataclasses import replace

from precond.engine.judging.report import Ranked

USER = "user"
"""The attribute of the agent's state that holds the other party (`self.user.messages`, `self.user.last_said`)."""


def about_the_call(ranked: Ranked, params: Sequence[str]) -> Ranked:
    """`ranked` without its assumed rules that name neither a parameter nor the user (module docstring)."""
    names = set(params) - {"self"}
    dropped = [c.representative.expression for c in ranked.chosen
               if ranked.decided.get(c.representative.expression) == "assumed"
               and not _reads(c.representative.expression) & (names | {USER})]
    if not dropped:
        return ranked
    reason = ("dropped: assumed, and about no part of the call (neither an argument, nor what was read of one, nor "
              "the user's words): every tool result overwrites it, so no policy can require it")
    return replace(ranked, chosen=[c for c in ranked.chosen if c.representative.expression not in dropped],
                   reasons={**ranked.reasons, **dict.fromkeys(dropped, reason)},
                   decided={e: d for e, d in ranked.decided.items() if e not in dropped})


def _reads(expression: str) -> set[str]:
    """The plain names an expression reads and the attributes it reads of `self` (`self.user` gives 'user')."""
    try:
        tree = ast.parse(expression, mode="eval")
    except SyntaxError:
        return set()
    found = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    found |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
              and n.value.id == "self"}
    return found
