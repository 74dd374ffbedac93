from sandbox.types import Point
from worker.ranking import ActionEvidence, Candidate, cluster, informative, rank, subsumption


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


def test_recency_prefers_conditions_made_true_since_the_last_action() -> None:
    # one demo, positions 0..3, the action at position 3; the agent last acted at position 0.
    points = [Point(0, p, ()) for p in range(4)]
    evidence = ActionEvidence(points, [Point(0, 3, ())], {(0, 3): 1})
    trigger = c("trigger", "1011")  # false at position 1, after the agent's last action: enables it
    phase = c("phase", "0111")      # true ever since the agent last acted: describes the phase
    both = cluster([trigger, phase])
    assert [k.representative.expression for k in rank("subsumption", both, evidence)] == ["trigger", "phase"]
    assert [k.representative.expression for k in rank("recency", both, evidence)] == ["trigger"]


def test_recency_falls_back_to_subsumption_when_nothing_was_triggered() -> None:
    points = [Point(0, p, ()) for p in range(4)]
    evidence = ActionEvidence(points, [Point(0, 3, ())], {(0, 3): 1})
    phase = cluster([c("phase", "0111"), c("wider", "1111")])
    assert [k.representative.expression for k in rank("recency", phase, evidence)] == ["phase"]
