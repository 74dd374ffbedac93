"""Argument domains: admissible-command parsing and the points built for ALFWorld and SGD."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from precond.evaluation.domains import action_positions, alfworld_points, gt_assertions, load_sgd, parse_command
from precond.sandbox.types import Point


@pytest.mark.parametrize(("command", "parsed"), [
    ("go to cabinet 1", ("goto", ("cabinet 1",))),
    ("open drawer 2", ("open", ("drawer 2",))),
    ("close drawer 2", ("close", ("drawer 2",))),
    ("take apple 1 from countertop 2", ("take", ("apple 1", "countertop 2"))),
    ("put apple 1 in/on fridge 1", ("put", ("apple 1", "fridge 1"))),
    ("put apple 1 in fridge 1", ("put", ("apple 1", "fridge 1"))),
    ("put apple 1 on table 1", ("put", ("apple 1", "table 1"))),
    ("clean mug 2 with sinkbasin 1", ("clean", ("mug 2", "sinkbasin 1"))),
    ("heat egg 1 with microwave 1", ("heat", ("egg 1", "microwave 1"))),
    ("cool bread 1 with fridge 1", ("cool", ("bread 1", "fridge 1"))),
    ("use desklamp 1", ("toggle", ("desklamp 1",))),
    ("look", None), ("inventory", None), ("examine shelf 1", None),
    ("slice potato 1 with knife 1", None),
])
def test_parse_command(command: str, parsed: tuple[str, tuple[str, ...]] | None) -> None:
    assert parse_command(command) == parsed


def _action(t: int, fn: str, args: list[str], in_spec: bool = True) -> dict[str, Any]:
    return {"kind": "action", "obj": "agent", "fn": fn, "args": args, "t": t, "in_spec": in_spec}


def _observation(t: int) -> dict[str, Any]:
    return {"kind": "observation", "obj": "agent", "fn": "update_visible_objects", "args": [], "t": t}


TRAJECTORY = {"steps": [
    _observation(0),
    _action(1, "goto", ["shelf 1"]), _observation(1),
    _action(2, "examine", ["shelf 1"], in_spec=False),
    _action(3, "take", ["mug 1", "shelf 1"]), _observation(3),
]}
ADMISSIBLE = [
    ["go to shelf 1", "go to desk 1", "look"],
    ["examine shelf 1", "take mug 1 from shelf 1", "take pen 1 from shelf 1", "go to desk 1"],
    ["take mug 1 from shelf 1", "go to desk 1", "open drawer 1"],
]


def test_positions_skip_the_setup_lines_and_out_of_spec_actions() -> None:
    positions = [p for p, _ in action_positions(TRAJECTORY)]
    # body: env=, agent=, observation(0), goto, observation(1), take, observation(3); examine is not written
    assert positions == [3, -1, 5]


def test_two_argument_actions_use_the_state_offers_one_argument_actions_the_trajectory_union() -> None:
    points = alfworld_points(TRAJECTORY, ADMISSIBLE, 7, ["goto", "take", "open"], mode="state")
    assert points["Agent.take"] == [Point(7, 5, ("mug 1", "shelf 1"))]  # offered before the take (t=3) only
    assert points["Agent.goto"] == [Point(7, p, (r,)) for p in (3, 5) for r in ("desk 1", "shelf 1")]
    assert points["Agent.open"] == [Point(7, 3, ("drawer 1",)), Point(7, 5, ("drawer 1",))]


def test_trajectory_mode_uses_the_union_for_two_argument_actions_too() -> None:
    points = alfworld_points(TRAJECTORY, ADMISSIBLE, 0, ["take"], mode="trajectory")
    offered = [("mug 1", "shelf 1"), ("pen 1", "shelf 1")]
    assert points["Agent.take"] == [Point(0, p, a) for p in (3, 5) for a in offered]


def test_gt_assertions_are_read_per_method() -> None:
    spec = "class Agent:\n  def put(self, obj, recep):\n    assert self.inventory == obj\n    assert recep\n"
    assert gt_assertions(spec, "Agent") == {"Agent.put": ["self.inventory == obj", "recep"]}


def test_sgd_points_cover_every_step_and_argument(tmp_path: Path) -> None:
    dialog = {"dialogue_id": "d1", "steps": [{"kind": "user_act"}, {"kind": "system_act"}],
              "program": "user = USER()\nsystem = SYSTEM(user)\nuser.HI()\nsystem.ASK('a')\n"}
    spec = "class SYSTEM:\n  def ASK(self, slot): pass\n  def BYE(self): pass\n"
    data = {"service": "Toy_1", "spec_program": spec,
            "system_actions": ["ASK", "BYE"], "system_action_args": {"ASK": ["a", "b"]},
            "gt_preconditions": {"ASK": ["True"]}, "demos": [dialog], "test": [dialog]}
    path = tmp_path / "Toy_1.json"
    path.write_text(json.dumps(data))
    domain = load_sgd(path)
    assert domain.points["SYSTEM.ASK"] == [Point(0, p, (v,)) for p in (2, 3) for v in ("a", "b")]
    assert domain.points["SYSTEM.BYE"] == [Point(0, 2, ()), Point(0, 3, ())]
    assert domain.actions == ("SYSTEM.ASK", "SYSTEM.BYE")
