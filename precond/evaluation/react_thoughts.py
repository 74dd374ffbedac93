"""ReAct's thoughts for the ALFWorld demonstrations: the paper's hand-written `think:` lines, as comments.

The twelve ALFWorld demonstrations are the ReAct prompts' `act_*` episodes; the same prompts file has each one
again as `react_*`, with the thoughts its authors wrote by hand between the actions (`ysymyth/ReAct`,
`prompts/alfworld_3prompts.json`, MIT). `precond/evaluation/data/alfworld_react_thoughts.json` keeps, per episode,
each thought and the index of the action it precedes; `with_thoughts` writes them into a demonstration's
program as `# think: ...` lines, the form `options.think` has the model write before each action.

    python -m precond.evaluation.react_thoughts PROMPTS.json   # rebuild the data file from the ReAct prompts
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

DATA = Path(__file__).resolve().parent / "data" / "alfworld_react_thoughts.json"
ACTING = "agent."
"""How an action line of an ALFWorld program starts (observations are `agent.update_...`/`add_...` too)."""
OBSERVING = ("agent.update_visible_objects(", "agent.add_inventory(", "agent.remove_inventory(")


def thought_positions(transcript: str) -> tuple[list[tuple[int, str]], list[str]]:
    """The thoughts of a ReAct transcript, each with the index of the action it precedes, and the actions."""
    thoughts: list[tuple[int, str]] = []
    actions: list[str] = []
    for line in transcript.splitlines():
        if not line.startswith(">"):  # the prompts write both "> go to" and ">go to"
            continue
        text = line[1:].strip()
        if text.startswith("think:"):
            thoughts.append((len(actions), text.removeprefix("think:").strip()))
        else:
            actions.append(text)
    return thoughts, actions


def _action_lines(program: str) -> list[int]:
    lines = program.splitlines()
    return [i for i, line in enumerate(lines)
            if line.strip().startswith(ACTING) and not line.strip().startswith(OBSERVING)]


def with_thoughts(program: str, thoughts: list[tuple[int, str]]) -> str:
    """The program with each thought as a `# think:` line before the action it precedes (at its indentation)."""
    lines = program.splitlines()
    actions = _action_lines(program)
    before: dict[int, list[str]] = {}
    for index, text in thoughts:
        if index < len(actions):
            before.setdefault(actions[index], []).append(text)
    out = []
    for i, line in enumerate(lines):
        indent = line[: len(line) - len(line.lstrip())]
        out += [f"{indent}# think: {text}" for text in before.get(i, [])]
        out.append(line)
    return "\n".join(out) + "\n"


def load() -> dict[str, list[tuple[int, str]]]:
    """Episode key (the demonstration's `source.key`, `act_put_0`) → its thoughts."""
    data = json.loads(DATA.read_text(encoding="utf-8"))
    return {key: [(int(i), str(t)) for i, t in rows] for key, rows in data["thoughts"].items()}


def build(prompts: dict[str, str], demos: list[dict[str, Any]]) -> dict[str, Any]:
    """The data file's content: for every demonstration, the thoughts of its `react_*` twin, which must take the
    same actions (checked: the thoughts are placed by action index)."""
    thoughts: dict[str, list[tuple[int, str]]] = {}
    for demo in demos:
        key = demo["source"]["key"]
        found, actions = thought_positions(prompts[key.replace("act_", "react_", 1)])
        _, expected = thought_positions(prompts[key])
        if actions != expected:
            raise ValueError(f"{key}: the ReAct episode takes other actions than the Act one")
        thoughts[key] = found
    return {"source": {"repo": "ysymyth/ReAct", "path": "prompts/alfworld_3prompts.json",
                       "commit": "6bdb3a1ffa4d4e2ee2cc8bfd9ac2ce04e43f4ff9", "license": "MIT",
                       "copyright": "Copyright (c) 2023 Shunyu Yao"},
            "thoughts": thoughts}


if __name__ == "__main__":
    from precond.evaluation.settings import DataSettings

    demos = json.loads((DataSettings().path("alfworld") / "demos.json").read_text())["trajectories"]
    DATA.parent.mkdir(exist_ok=True)
    DATA.write_text(json.dumps(build(json.loads(Path(sys.argv[1]).read_text()), demos), indent=1) + "\n")
