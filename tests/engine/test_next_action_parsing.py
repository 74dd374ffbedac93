from precond.engine.acting.next_action import append_line, classify

RECEIVERS = {"user": "USER", "system": "SYSTEM"}
ACTIONS = {"SYSTEM.REQUEST", "SYSTEM.INFORM"}


def test_action_call_is_normalised() -> None:
    p = classify('  system.REQUEST("city")', RECEIVERS, ACTIONS)
    assert p.call == "system.REQUEST('city')" and p.reason is None


def test_non_actions_say_why() -> None:
    assert classify("user.INFORM('city')", RECEIVERS, ACTIONS).reason == "USER.INFORM is not an action function"
    assert classify("", RECEIVERS, ACTIONS).reason == "empty line"
    assert classify("system.REQUEST(", RECEIVERS, ACTIONS).reason == "not valid Python"
    assert classify("x = 1", RECEIVERS, ACTIONS).reason == "not a single method call"


def test_append_keeps_the_episode_indentation() -> None:
    history = "def episode():\n    agent = Agent(env)\n    agent.goto('a')\n"
    assert append_line(history, "agent.open('a')").endswith("\n    agent.open('a')\n")
    assert append_line("user = USER()\n", "system.GOODBYE()") == "user = USER()\nsystem.GOODBYE()\n"
