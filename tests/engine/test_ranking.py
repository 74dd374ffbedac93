from precond.engine.judging.ranking import (
    ActionEvidence,
    Candidate,
    cluster,
    enabling_rate,
    explain,
    informative,
    rank,
    subsumption,
    within_budget,
    zero_shot,
)
from precond.sandbox.types import Point


def c(expression: str, bits: str) -> Candidate:
    return Candidate(expression, "model", int(bits[::-1], 2))


def test_equal_sets_cluster_and_shortest_represents() -> None:
    clusters = cluster([c("self.q == True", "0110"), c("self.q", "0110"), c("x", "0111")])
    assert [len(k.members) for k in clusters] == [2, 1]
    assert clusters[0].representative.expression == "self.q"


def test_subsumption_keeps_minimal_sets_only() -> None:
    # the appendix example: query_success (0110) subsumes `is not None` (0111); requested (1100) is incomparable
    clusters = cluster([c("q is not None", "0111"), c("q", "0110"), c("requested", "1100")])
    assert [k.representative.expression for k in subsumption(clusters)] == ["q", "requested"]


def test_trivial_and_empty_sets_are_uninformative() -> None:
    clusters = cluster([c("True", "1111"), c("False", "0000"), c("q", "0110")])
    assert [k.representative.expression for k in informative(clusters, 4)] == ["q"]


def _evidence() -> ActionEvidence:
    # one demo, positions 0..9; the action occurs at 9; the agent's previous turn ended before position 7.
    points = [Point(0, p, ()) for p in range(10)]
    return ActionEvidence(points, [Point(0, 9, ())], {(0, 9): 7})


def test_recency_keeps_only_enabling_conditions() -> None:
    trigger = c("trigger", "1111100001")  # false at 7..8, during the observations before the action
    phase = c("phase", "0000111111")      # false early, true ever since before the last turn
    both = cluster([trigger, phase])
    assert [k.representative.expression for k in rank("subsumption", both, _evidence())] == ["trigger", "phase"]
    assert [k.representative.expression for k in rank("recency", both, _evidence())] == ["trigger"]


def _two_calls() -> ActionEvidence:
    """Positions 0..9 for two argument values; the action is called with 'a' and with 'b' at position 9."""
    points = [Point(0, p, (arg,)) for p in range(10) for arg in ("a", "b")]
    occurrences = [Point(0, 9, ("a",)), Point(0, 9, ("b",))]
    return ActionEvidence(points, occurrences, {(0, 9): 7}, params=("slot",))


def _rate(evidence: ActionEvidence, name: str, bits: str) -> float:
    """Bits per position, the same for both argument values."""
    index = {p: bit for bit, p in enumerate(evidence.points)}
    doubled = "".join(b * (len(evidence.points) // 10) for b in bits)
    return enabling_rate(cluster([c(name, doubled)])[0], evidence, index)


def test_enabling_rate_tells_triggers_and_argument_conditions_from_phases() -> None:
    evidence = _two_calls()
    assert _rate(evidence, "made true since the last turn", "1111100001") == 1.0
    assert _rate(evidence, "not self.informed[slot]", "1111111111") == 1.0  # about the argument
    assert _rate(evidence, "not self.selected", "1111111111") == 0.0        # global, never made true: a phase
    assert _rate(evidence, "phase", "0000111111") == 0.0


def test_a_parameter_seen_with_one_value_is_a_constant_in_disguise() -> None:
    single = ActionEvidence(_two_calls().points, [Point(0, 9, ("a",))], {(0, 9): 7}, params=("slot",))
    assert _rate(single, "not self.informed[slot]", "1111111111") == 0.0


def test_marginal_stops_adding_conditions_that_trim_little() -> None:
    tight = c("tight", "0000111111")
    near_trivial = c("near trivial", "1111011111")  # incomparable with tight; trims 1 of the 6 points it allows
    kept = rank("marginal", cluster([tight, near_trivial]), _evidence())
    assert [k.representative.expression for k in kept] == ["tight"]
    assert [k.representative.expression for k in rank("subsumption", cluster([tight, near_trivial]), _evidence())] \
        == ["tight", "near trivial"]


def test_zero_shot_keeps_the_most_proposed_assertion_only_when_samples_agree() -> None:
    valid = [c("self.env.get_property(recep, 'open')", "0"), c("False", "0"), c("recep", "0")]
    votes = {"self.env.get_property(recep, 'open')": 3, "False": 5, "recep": 2}
    kept = zero_shot(valid, votes, ["recep"])
    assert [k.representative.expression for k in kept] == ["self.env.get_property(recep, 'open')"]
    assert zero_shot(valid, {"False": 9, "recep": 1}, ["recep"]) == []  # constants say nothing; 1 vote is noise


def test_a_rule_stricter_only_by_refusing_demonstrated_calls_does_not_subsume() -> None:
    # occurrences at bits 0 and 1; `strict` refuses occurrence 1 (a tolerated exception), `true` allows both
    occurrences = int("11000000"[::-1], 2)
    true, strict = c("true", "11110000"), c("strict", "10110000")
    clusters = cluster([true, strict])
    assert [k.representative.expression for k in subsumption(clusters)] == ["strict"]  # without evidence: eq. hopt
    kept = subsumption(clusters, occurrences)
    assert [k.representative.expression for k in kept] == ["true", "strict"]
    tighter = c("tighter", "11100000")  # stricter, and allows every occurrence `true` allows: subsumes it
    assert [k.representative.expression for k in subsumption(cluster([true, tighter]), occurrences)] == ["tighter"]


def test_a_tolerated_exception_never_counts_as_enabling() -> None:
    # the condition is false at 7..9: false before the call, and at the call itself (an exception)
    evidence = _evidence()
    index = {p: bit for bit, p in enumerate(evidence.points)}
    assert enabling_rate(cluster([c("slipped", "1111111000")])[0], evidence, index) == 0.0


def test_thin_actions_rank_like_never_demonstrated_ones() -> None:
    evidence = ActionEvidence([Point(0, p, ()) for p in range(4)], [Point(0, 3, ())], {(0, 3): 2}, thin=True)
    coincidence = c("self.q", "0001")
    reasons = explain("recency", [coincidence], [], [], evidence, {})
    assert "only 1 occurrence, too few" in reasons["self.q"] and "dropped" in reasons["self.q"]


def test_kept_rules_together_refuse_no_more_than_the_tolerance() -> None:
    # 20 occurrences at bits 0..19, 10 other points; tolerance 10%: the conjunction may refuse 2 calls
    points = [Point(0, p, ()) for p in range(30)]
    evidence = ActionEvidence(points, points[:20], {}, occurrence_mask=(1 << 20) - 1, tolerance=0.1)
    held = c("held", "1" * 20 + "0" * 10)
    slip = c("slip", "0" + "1" * 19 + "1" * 5 + "0" * 5)  # refuses occurrence 0
    other = c("other", "1" + "00" + "1" * 17 + "0" * 10)  # refuses occurrences 1 and 2
    chosen = within_budget(cluster([held, slip, other]), evidence)
    assert [k.representative.expression for k in chosen] == ["held", "slip"]  # 1 + 2 refused > 2: `other` out
    strict = ActionEvidence(points, points[:20], {}, occurrence_mask=(1 << 20) - 1)
    assert len(within_budget(cluster([held, slip, other]), strict)) == 3  # tolerance 0: nothing to budget


def _budgeted(n_occurrences: int, n_others: int) -> ActionEvidence:
    points = [Point(0, p, ()) for p in range(n_occurrences + n_others)]
    return ActionEvidence(points, points[:n_occurrences], {}, occurrence_mask=(1 << n_occurrences) - 1,
                          tolerance=0.05)


def test_a_strongly_separating_rule_may_refuse_more_calls_than_the_budget() -> None:
    # 40 calls (budget 2), 60 other points: holds at 34 calls (6 slips, 15%) and at 10 of the other points
    evidence = _budgeted(40, 60)
    slipped = c("slipped", "0" * 6 + "1" * 34 + "1" * 10 + "0" * 50)
    assert [k.representative.expression for k in within_budget(cluster([slipped]), evidence)] == ["slipped"]


def test_extra_exceptions_need_separation_beyond_the_rules_already_kept() -> None:
    # `held` allows the 40 calls and 12 of the 60 other points; `narrower` holds at 34 calls and 10 other
    # points, all among those 12: strong on its own (10 of 60), but next to `held` it holds at 10 of 12 of
    # the points still allowed, so its 6 exceptions are a correlation, not slips
    evidence = _budgeted(40, 60)
    held = c("held", "1" * 40 + "1" * 12 + "0" * 48)
    narrower = c("narrower", "0" * 6 + "1" * 34 + "1" * 10 + "0" * 50)
    assert [k.representative.expression for k in within_budget(cluster([held, narrower]), evidence)] == ["held"]
