"""ReAct's thoughts in the ALFWorld demonstrations: every demonstration has its hand-written thoughts, each
placed before the action its ReAct twin took next, as comments that leave the program's statements as they were."""

from __future__ import annotations

import ast
import json
from pathlib import Path

from precond.evaluation.react_thoughts import load, thought_positions, with_thoughts

DEMOS = json.loads((Path(__file__).resolve().parents[1] / "fixtures" / "data" / "alfworld" / "demos.json")
                   .read_text())["trajectories"]


def test_every_demonstration_has_its_thoughts_before_the_actions_they_precede() -> None:
    thoughts = load()
    assert sorted(thoughts) == sorted(d["source"]["key"] for d in DEMOS)
    for demo in DEMOS:
        found = thoughts[demo["source"]["key"]]
        _, actions = thought_positions(demo["transcript"])
        assert found and all(0 <= index < len(actions) for index, _ in found)
        program = with_thoughts(demo["program"], found)
        assert ast.dump(ast.parse(program)) == ast.dump(ast.parse(demo["program"]))  # comments only
        lines = program.splitlines()
        thought_lines = [i for i, line in enumerate(lines) if line.strip().startswith("# think: ")]
        assert len(thought_lines) == len(found)
        for i in thought_lines:  # each before an action (or another thought), at the body's indentation
            following = next(line for line in lines[i + 1:] if not line.strip().startswith("#"))
            assert following.strip().startswith("agent.") and lines[i].startswith("    # think: ")


def test_the_first_thought_states_the_plan_before_the_first_action() -> None:
    demo = DEMOS[0]
    program = with_thoughts(demo["program"], load()[demo["source"]["key"]])
    first_action = next(line for line in program.splitlines() if line.strip().startswith("agent.goto("))
    before = program[: program.index(first_action)]
    assert "# think: To solve the task, I need to find and take a sparybottle" in before
