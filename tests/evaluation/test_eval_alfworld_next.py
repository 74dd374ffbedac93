"""ALFWorld next-action scoring's pure parts (precond/evaluation/alfworld_next.py), on the fixture trajectories."""

from __future__ import annotations

import ast
import json
from pathlib import Path
from typing import Any

from precond.evaluation.alfworld_next import (
    Episode,
    history_before,
    predicted_command,
    sample_episodes,
    scored,
    summarize,
)
from precond.evaluation.domains import action_positions

DATA = Path(__file__).resolve().parents[1] / "fixtures" / "data" / "alfworld"


def _trajectories() -> list[dict[str, Any]]:
    data: list[dict[str, Any]] = json.loads((DATA / "test.json").read_text())["trajectories"]
    return data


def test_history_ends_just_before_the_step_predicted() -> None:
    trajectory = _trajectories()[0]
    position, step = next((p, s) for p, s in action_positions(trajectory) if p >= 0)
    history = history_before(trajectory["program"], position)
    assert history.startswith("def ") and "agent = Agent(env)" in history
    following = trajectory["program"][len(history):].splitlines()[0].strip()
    assert following.startswith(f"agent.{step['fn']}(")


def test_a_call_is_read_as_the_simulator_command_it_is() -> None:
    assert predicted_command("agent.take('apple 1', 'table 1')") == ("take", ("apple 1", "table 1"))
    assert predicted_command("agent.goto('bed 1')") == ("goto", ("bed 1",))
    assert predicted_command(None) is None and predicted_command("go to bed 1") is None


def test_episodes_are_sampled_by_seed_with_steps_spread_over_each() -> None:
    trajectories = _trajectories()
    admissible = {t["id"]: [[]] * 100 for t in trajectories[:6]}
    demos = json.loads((DATA / "demos.json").read_text())["trajectories"]
    first = sample_episodes(trajectories, demos, admissible, 4, 3, seed=0)
    assert [e.id for e in first] == [e.id for e in sample_episodes(trajectories, demos, admissible, 4, 3, seed=0)]
    assert len(first) == 4 and all(e.id in admissible for e in first)
    assert all(len(e.steps) == 3 and e.steps == sorted(e.steps, key=lambda s: s[0]) for e in first)
    for episode in first:  # ReAct's rows show the same demonstration with its thoughts
        assert episode.react_demonstration.count("# think: ") >= 4
        assert ast.dump(ast.parse(episode.react_demonstration)) == ast.dump(ast.parse(episode.demonstration))


def test_summary_gives_shares_with_intervals_and_paired_differences() -> None:
    def rows(admissible: list[bool]) -> list[dict[str, Any]]:
        return [{"episode": f"e{k}", "admissible": a, "expert": False, "seconds": 1.0, "error": None}
                for k, a in enumerate(admissible)]

    out = {r["config"]: r for r in summarize({"base": rows([False, True]), "new": rows([True, True])}, "base")}
    assert out["new"]["admissible"]["estimate"] == 1.0 and out["base"]["admissible"]["estimate"] == 0.5
    assert out["new"]["admissible_diff"]["estimate"] == 0.5 and "admissible_diff" not in out["base"]


def test_a_line_that_is_no_command_is_never_admissible() -> None:
    """The simulator offers commands the spec has no action for (`look`, `inventory`): they parse to no command,
    and a cut-off or comment line parses to none either; that must not make it count as offered."""
    step = {"t": 1, "fn": "goto", "args": ["desk 1"]}
    episode = Episode("e", "", "", "", [], [["look", "inventory", "go to desk 1", "go to bed 1"]])
    cases = (("agent.goto('bed 1')", True, False), ("agent.goto('desk 1')", True, True),
             ("agent.goto('desk 1', 'bed", False, False), ("# think: look around", False, False), (None, False, False))
    for call, admissible, expert in cases:
        out = scored({"call": call}, episode, step)
        assert (out["admissible"], out["expert"], out["episode"]) == (admissible, expert, "e"), call
