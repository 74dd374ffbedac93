"""Guards built in several threads at once: an agent's framework runs tools in an executor, and each may build or
load a guard. CPython 3.11's AST constructor shares its recursion depth between threads, so unserialized parses
can end with `SystemError: AST constructor recursion depth mismatch` (precond_client/parsing.py)."""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from precond.convert.openai import convert
from precond_client.guard import Guard

CARDS = Path(__file__).resolve().parents[1] / "fixtures" / "tools_domains" / "cards"
RULES = {"AGENT.freeze_card": [
    "card_id in self.results['get_card_details'] and self.results['get_card_details'][card_id]['status'] in "
    "('active',)", "any(card_id in y['card_ids'] for y in self.seen['get_customer_profile'])"]}


def test_guards_built_in_many_threads_at_once_all_build_and_agree() -> None:
    runs = json.loads((CARDS / "trajectories.json").read_text())
    spec = convert(runs, json.loads((CARDS / "tools.json").read_text()), writes=set(
        json.loads((CARDS / "writes.json").read_text()))).spec
    history = runs[0][:-2]  # the freeze's result left out: the call judged after the card was read

    def build(_: int) -> bool:
        guard = Guard(spec, RULES)
        return guard.check(history, "freeze_card", {"card_id": "K11"}).allowed

    with ThreadPoolExecutor(8) as pool:
        verdicts = list(pool.map(build, range(400)))
    assert verdicts == [True] * 400
