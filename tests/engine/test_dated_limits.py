"""A limit against today kept beside the shorter rule the demonstrations cannot tell it from
(precond/engine/judging/dated_limits.py)."""

from precond.engine.judging.dated_limits import with_dated_limits
from precond.engine.judging.ranking import Candidate, Cluster
from precond.engine.judging.report import Ranked

READ = "loan_id in self.results['get_loan']"
UNFLOWN = f"{READ} and all(x['date'] >= '2024-05-15' for x in self.results['get_loan'][loan_id]['visits'])"
OLDER = f"{READ} and any(x['dob'] < '2024-05-15' for x in self.results['get_loan'][loan_id]['members'])"


def ranked(*members: str) -> Ranked:
    cluster = Cluster(tuple(Candidate(e, "enumerate", 0b111) for e in members))
    return Ranked(results=[], valid=list(cluster.members), clusters=[cluster], chosen=[cluster],
                  decided={READ: "established"})


def test_a_dated_limit_equivalent_to_the_kept_rule_is_kept_too_as_assumed() -> None:
    out = with_dated_limits(ranked(READ, UNFLOWN, OLDER), {READ, UNFLOWN, OLDER})
    assert [c.representative.expression for c in out.chosen] == [READ, UNFLOWN]
    assert out.decided[UNFLOWN] == "assumed" and out.decided[READ] == "established"


def test_a_limit_not_among_the_tools_conditions_is_not_added() -> None:
    out = with_dated_limits(ranked(READ, UNFLOWN), {READ})
    assert [c.representative.expression for c in out.chosen] == [READ]
