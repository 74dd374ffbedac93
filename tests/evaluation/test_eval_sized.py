"""The sized next-action evaluation's pure parts: the seeded sample of dialogs, per-dialog units, the summary,
and the memo that lets configurations share completions (precond/evaluation/sized.py, precond/evaluation/memo.py)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

from precond.engine.models import Sampling
from precond.evaluation.cache import JsonCache
from precond.evaluation.memo import MemoModel
from precond.evaluation.sized import sample_dialogs, summarize, units
from precond_client.schemas import ModelInfo


def _dialog(name: str, system_turns: int) -> dict[str, Any]:
    turns = [{"speaker": "SYSTEM", "steps": [k, k + 1]} for k in range(system_turns)]
    return {"dialogue_id": name, "turns": [{"speaker": "USER", "steps": [0, 1]}, *turns]}


def test_dialogs_are_sampled_whole_and_by_seed_until_enough_turns() -> None:
    dialogs = [_dialog(f"d{k}", 3) for k in range(10)]
    first = sample_dialogs(dialogs, 7, seed=0)
    assert len(first) == 3  # 3 + 3 < 7 <= 9 turns
    assert [d["dialogue_id"] for d in sample_dialogs(dialogs, 7, seed=0)] == [d["dialogue_id"] for d in first]
    assert {d["dialogue_id"] for d in sample_dialogs(dialogs, 7, seed=1)} != {d["dialogue_id"] for d in first}
    assert len(sample_dialogs(dialogs, 1000, seed=0)) == 10


def _row(dialog: str, turn: int, predicted: list[str], reference: list[str], compatible: list[bool],
         seconds: float = 1.0) -> dict[str, Any]:
    return {"dialog": dialog, "turn": turn, "predicted": predicted, "reference": reference,
            "compatible": compatible, "seconds": seconds, "domain": "D"}


def test_segments_of_a_turn_are_scored_together_and_units_are_dialogs() -> None:
    rows = [_row("a", 1, ["x()"], ["x()", "y()"], [True]), _row("a", 1, ["y()"], [], [False]),
            _row("b", 1, ["z()"], ["x()"], [True])]
    f1, compat = units(rows)
    assert f1 == {"a": [1.0], "b": [0.0]}
    assert compat == {"a": [1.0, 0.0], "b": [1.0]}


def test_summary_pairs_every_config_with_the_baseline_on_the_same_dialogs() -> None:
    base = [_row("a", 1, ["x()"], ["y()"], [False]), _row("b", 1, ["x()"], ["y()"], [True], 3.0)]
    better = [_row("a", 1, ["y()"], ["y()"], [True]), _row("b", 1, ["y()"], ["y()"], [True], 2.0)]
    rows = {r["config"]: r for r in summarize({"base": base, "better": better}, "base")}
    assert "f1_diff" not in rows["base"]
    assert rows["better"]["f1_diff"]["estimate"] == 1.0 and rows["better"]["f1_diff"]["low"] == 1.0
    assert rows["better"]["compatibility"]["estimate"] == 1.0 and rows["base"]["compatibility"]["estimate"] == 0.5
    assert rows["better"]["turns"] == 2 and rows["better"]["latency_p95_s"] == 2.0


class CountingModel:
    info = ModelInfo(name="counting", device="cpu", dtype="none")
    known_calls: tuple[str, ...] = ()

    def __init__(self) -> None:
        self.calls = 0

    def complete(self, prefix: str, suffixes: Sequence[str], n: int, sampling: Any, stop: str,
                 should_stop: Callable[[], bool] | None = None) -> list[list[str]]:
        self.calls += 1
        return [[f"{prefix}{s}:{n}"] for s in suffixes]


def test_a_remembered_completion_is_not_computed_again_and_its_time_is_replayed(tmp_path: Path) -> None:
    inner = CountingModel()
    memo = MemoModel(inner, JsonCache(tmp_path))  # type: ignore[arg-type]
    greedy = Sampling(0.0, 0.95, 8, 0)
    first = memo.complete("p", ["a"], 1, greedy, "line")
    assert memo.take_replayed() == 0.0
    assert memo.complete("p", ["a"], 1, greedy, "line") == first and inner.calls == 1
    assert memo.take_replayed() > 0.0 and memo.take_replayed() == 0.0
    memo.complete("p", ["a"], 1, Sampling(0.8, 0.95, 8, 1), "line")
    assert inner.calls == 2  # other sampling, other question
    again = MemoModel(CountingModel(), JsonCache(tmp_path))  # type: ignore[arg-type]
    assert again.complete("p", ["a"], 1, greedy, "line") == first  # resumable: on disk


def test_a_fine_tuned_model_does_not_answer_from_the_base_models_memo(tmp_path: Path) -> None:
    base, tuned = CountingModel(), CountingModel()
    tuned.info = ModelInfo(name="counting", device="cpu", dtype="none", adapter="bc@0123456789ab")
    greedy = Sampling(0.0, 0.95, 8, 0)
    MemoModel(base, JsonCache(tmp_path)).complete("p", ["a"], 1, greedy, "line")  # type: ignore[arg-type]
    MemoModel(tuned, JsonCache(tmp_path)).complete("p", ["a"], 1, greedy, "line")  # type: ignore[arg-type]
    assert tuned.calls == 1  # computed: the same prompt is another question for another policy


@pytest.mark.parametrize("seed", [0, 5])
def test_sample_is_deterministic_across_calls(seed: int) -> None:
    dialogs = [_dialog(f"d{k}", 2) for k in range(6)]
    assert sample_dialogs(dialogs, 5, seed) == sample_dialogs(list(dialogs), 5, seed)


class CheckOnly:
    """An engine that can judge calls but must not be asked to predict (a cached-only summary)."""

    def next_action(self, request: Any) -> Any:
        raise AssertionError("a cached-only summary predicted")

    def check(self, request: Any) -> Any:
        from precond_client.schemas import CallVerdict, CheckResponse

        return CheckResponse(results=[CallVerdict(call=c, allowed=True) for c in request.calls])


def test_cached_only_takes_the_dialogs_every_config_finished(tmp_path: Path) -> None:
    from precond.evaluation.domains import Domain
    from precond.evaluation.policy import parse_policy_config, segments
    from precond.evaluation.sized import Task, finished, run

    program = "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM('a')\nsystem.REQUEST('b')\n"
    dialogs = [{"dialogue_id": name, "program": program, "turns": [{"speaker": "USER", "steps": [0, 1]},
                                                                  {"speaker": "SYSTEM", "steps": [1, 2]}],
                "steps": [{"kind": "user_act"}, {"kind": "system_act"}]} for name in ("d1", "d2")]
    domain = Domain("D", "sgd", "class SYSTEM: ...", (), ("SYSTEM.REQUEST",), (), (), {}, {})
    configs = [parse_policy_config("none/plain/shots=1"), parse_policy_config("inferred/constrained/shots=1")]
    cache = JsonCache(tmp_path)
    [segment] = segments(dialogs[0])
    done = {segment.key: {"predicted": ["system.REQUEST('b')"], "reference": list(segment.reference),
                          "seconds": 1.0, "error": None, "turn": segment.turn}}
    for config in configs:
        cache.put(done, "policy", "D", config.name, "d1")
    cache.put(done, "policy", "D", configs[0].name, "d2")  # d2: one config only
    task = Task(domain, dialogs, {})
    assert finished(cache, task, dialogs[0], configs) and not finished(cache, task, dialogs[1], configs)
    results = run(lambda task, config: CheckOnly(), [task], configs, cache, cached_only=True)
    assert {name: [r["dialog"] for r in rows] for name, rows in results.items()} == {
        c.name: ["d1"] for c in configs}
