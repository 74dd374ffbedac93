"""Runs grouped into tasks from their calls, when a simulated user's first words differ from run to run."""

from precond.engine.judging.run_tasks import tasks

USER = "user = USER()\nagent = AGENT(user)\n"


def run(words: str, *calls: str) -> str:
    return USER + f"user.says({words!r})\n" + "".join(f"{c}\nagent.result('x', 1, True, {{}})\n" for c in calls)


def test_runs_whose_first_calls_meet_are_one_task_whatever_the_user_first_says() -> None:
    a = run("Hi, please cancel XEHM4B.", "agent.get_reservation_details('XEHM4B')",
            "agent.cancel_reservation('XEHM4B')")
    b = run("Hello! I need to cancel my trips.", "agent.get_user_details('sophia_4574')",
            "agent.get_reservation_details('XEHM4B')")
    c = run("Hello! I need to cancel my trips.", "agent.get_user_details('mia_3668')")
    named = tasks([a, b, c])
    assert named[0] == named[1]
    assert named[2] not in (named[0], named[1])


def test_a_first_call_met_only_in_part_joins_no_task() -> None:
    a = run("Find me a flight.", "agent.search_direct_flight('JFK', 'SEA', '2024-05-20')")
    b = run("Find me a flight.", "agent.search_direct_flight('JFK', 'LAX', '2024-05-21')")
    assert len(set(tasks([a, b]))) == 2


def test_a_run_without_a_call_is_told_by_its_first_words() -> None:
    named = tasks([USER + "user.says('hi')\n", USER + "user.says('hi')\n", USER + "user.says('bye')\n"])
    assert named[0] == named[1] != named[2]
