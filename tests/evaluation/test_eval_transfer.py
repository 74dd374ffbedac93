"""Leave-one-domain-out priors (precond/evaluation/transfer.py): the held-out domain's priors are the other domains'
*inferred* rules, never any ground truth, and never its own."""

from __future__ import annotations

from pathlib import Path

from precond.evaluation.cache import JsonCache
from precond.evaluation.configs import parse_config
from precond.evaluation.domains import Domain
from precond.evaluation.transfer import sources_for
from precond_client.schemas import InferRequest, InferResponse, InferStats, StageCounts


def _domain(name: str) -> Domain:
    return Domain(name, "sgd", f"class SYSTEM:\n  def {name}(self): pass\n", (f"# {name}\n",), ("SYSTEM.GOODBYE",),
                  (), (), {}, {"SYSTEM.GOODBYE": ["GROUND_TRUTH"]})


def test_priors_are_the_other_domains_inferred_rules(tmp_path: Path) -> None:
    asked: list[str] = []

    def engine(request: InferRequest) -> InferResponse:
        asked.append(request.demonstrations[0])
        assert not request.options.prior_sources  # the other domains are inferred alone
        stats = InferStats(actions={}, total=StageCounts(), seconds={})
        return InferResponse(preconditions={"SYSTEM.GOODBYE": [f"inferred {request.demonstrations[0]}"]},
                             program="", stats=stats, candidates={})

    domains = [_domain(n) for n in ("A", "B", "C")]
    sources = sources_for(domains[0], domains, parse_config("enumerate/cautious"), JsonCache(tmp_path),
                          lambda: engine)
    assert [s.source for s in sources] == ["B", "C"]
    assert [s.rules for s in sources] == [{"SYSTEM.GOODBYE": ["inferred # B\n"]},
                                          {"SYSTEM.GOODBYE": ["inferred # C\n"]}]
    assert asked == ["# B\n", "# C\n"]
