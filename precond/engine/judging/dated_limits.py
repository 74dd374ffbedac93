"""A limit against today kept beside the rule the demonstrations cannot tell it from.

Ranking keeps one rule per cluster of conditions equivalent on the demonstrations, the shortest. A tool's
demonstrated calls seldom meet a record with an item dated before today (every cancelled reservation is still to
be flown), so "the reservation was read" and "the reservation was read and none of its flights is dated before
today" hold at the same points, and the shorter wins: the guard then allows a call on a trip already flown, a
state the demonstrations never reached. Where a chosen cluster holds such a limit among the tool's own conditions
(`tool_conditions`' `moments`: every item of a read's list dated today or later), it is kept too, as an assumed
rule (the evidence cannot tell it is the reason): on the demonstrations it refuses nothing the cluster allows,
so it only narrows what they never showed, to the side a policy that dates things takes.
"""

from __future__ import annotations

import re
from dataclasses import replace

from precond.engine.judging.ranking import Cluster
from precond.engine.judging.report import Ranked

DATED_LIMIT = re.compile(r"\ball\(x\[[^\]]+\] >= '\d{4}-\d{2}-\d{2}' for x in ")
"""`all(x['date'] >= '2024-05-15' for x in ...)`: no item of a read's list dated before today."""


def with_dated_limits(ranked: Ranked, policy: set[str]) -> Ranked:
    """`ranked` with each chosen cluster's dated limits among `policy` (the action's tool conditions) kept as
    assumed rules beside its representative (module docstring)."""
    have = {c.representative.expression for c in ranked.chosen}
    extra = [Cluster((m,)) for c in ranked.chosen for m in c.members
             if m.expression in policy and m.expression not in have and DATED_LIMIT.search(m.expression)]
    if not extra:
        return ranked
    texts = [c.representative.expression for c in extra]
    reason = ("kept: a limit against today, equivalent on the demonstrations to a rule kept (same cluster): no "
              "demonstrated call met an item dated before today, so nothing tells it from that rule; assumed")
    return replace(ranked, chosen=[*ranked.chosen, *extra], reasons={**ranked.reasons, **dict.fromkeys(texts, reason)},
                   decided={**ranked.decided, **dict.fromkeys(texts, "assumed")})
