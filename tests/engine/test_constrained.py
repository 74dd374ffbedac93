"""What the constrained mode enumerates (precond/engine/acting/constrained.py): static, no sandbox, no model."""

from __future__ import annotations

import ast
import math

from precond.engine.acting import constrained
from precond.engine.spec import parse_spec

SPEC = """class Env:
  def __init__(self):
    self.seen = set()
  def see(self, *objects): self.seen.update(objects)
class Agent:
  def __init__(self, env):
    self.env = env
  def goto(self, recep): pass
  def take(self, obj, recep): pass
  def wait(self, seconds=5): pass
  def look(self): return self.env.seen
"""
HISTORY = "env = Env()\nagent = Agent(env)\nenv.see('apple 1', 'table 1')\nagent.goto('table 1')\n"


def test_argument_values_by_parameter_name_with_what_was_seen_and_defaults() -> None:
    spec = parse_spec(SPEC)
    values, every = constrained.argument_values(spec, [ast.parse(HISTORY)])
    assert values["recep"] == ["table 1", "apple 1"]  # named by goto, then what was seen
    assert values["seconds"][0] == 5  # the spec's default
    assert "obj" not in values and set(every) >= {"apple 1", "table 1", 5}


def test_calls_are_enumerated_on_the_history_s_own_objects() -> None:
    spec = parse_spec(SPEC)
    values, every = constrained.argument_values(spec, [ast.parse(HISTORY)])
    found = constrained.enumerate_calls(spec, ["Agent.goto", "Agent.take"], {"agent": "Agent", "env": "Env"},
                                        values, every)
    assert "agent.goto('table 1')" in found.calls and "agent.take('apple 1', 'table 1')" in found.calls
    assert found.action["agent.take('apple 1', 'table 1')"] == "Agent.take"
    assert found.head["agent.goto('apple 1')"] == "agent.goto(" and not found.truncated
    assert constrained.enumerate_calls(spec, ["Agent.goto"], {"env": "Env"}, values, every).calls == []


def test_the_turn_ends_when_no_action_is_likelier_than_an_action() -> None:
    spec = parse_spec(SPEC)
    heads = constrained.turn_heads(spec, {"agent": "Agent", "env": "Env"}, ["Agent.goto", "Agent.take"])
    assert (heads.own, heads.others) == (["agent"], ["env"])  # where tokens end: not `agent.`
    assert set(heads.observations) == {"agent.wait", "agent.look"}  # the agent's methods that are no action
    log = math.log
    acting = {"agent": log(0.6), "agent.wait": log(0.05), "agent.look": log(0.05), "env": log(0.3)}
    assert not constrained.ends_turn(heads, acting)  # 0.3 + 0.1 < 0.6 - 0.1
    observing = acting | {"agent.look": log(0.3)}
    assert constrained.ends_turn(heads, observing)  # 0.3 + 0.35 > 0.6 - 0.35
    assert constrained.indentation("def f():\n    agent = Agent(env)\n") == "    "


def test_an_argument_that_is_not_the_last_is_scored_up_to_its_closing_quote() -> None:
    assert constrained.argument_texts("agent.take(", [], ["apple 1", 3], last=False) == [
        "agent.take('apple 1", "agent.take(3"]
    assert constrained.argument_texts("agent.take(", ["apple 1"], ["table 1"], last=True) == [
        "agent.take('apple 1', 'table 1')\n"]
