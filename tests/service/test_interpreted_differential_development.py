"""The interpreter's verdicts equal the sandbox's, field for field (test_interpreted_differential.py says how), on
the development data: every SGD domain under every condition the enumerator proposes for it, its learned rules
and the hand-written ones, each judged after a seeded sample of the prefixes of its first 3 dialogs (test dialogs
first; the sample is the same in every run, so a failure repeats); the first runs of the tau-bench airline and
retail calls under their learned rules (and the airline's hand-written clauses). Every prefix of every domain is
`python bench/interpreted_differential_bench.py`. A module of its own so that it runs beside the fixtures' one.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator

import pytest

from precond.engine.engine import Engine
from precond.evaluation.settings import DataSettings
from precond.sandbox import Sandbox
from precond.stack.differential import check_sgd_domain
from tests.client.test_guard_differential import CLAUSE
from tests.service.test_interpreted_differential import check_tau

pytestmark = pytest.mark.long  # collected first: pytest-xdist starts it first

PREFIXES = 12
"""Prefixes of a development SGD domain judged (of about 55): every rule set meets a dozen states a domain, and
the whole sweep stays a fraction of the suite's time."""
DEVELOPMENT_RUNS = 40
"""Runs of a development tau-bench domain learned from and judged (the first ones): enough for every kind of
verdict, and a bounded time in the suite (all 150 retail runs' inference alone takes minutes on two cores)."""


@pytest.fixture(scope="module")
def engine() -> Iterator[Engine]:
    with Sandbox(workers=2) as sandbox:
        yield Engine(sandbox, None)


@pytest.mark.timeout(3600)
def test_every_development_sgd_domain(engine: Engine) -> None:
    data = DataSettings().root / "sgd"
    paths = sorted(data.glob("*_*.json"))
    if not paths:
        pytest.skip(f"the development data is not here ({data}; PRECOND_DATA_DIR): the fixture test covers two "
                    "of its domains")
    seen: Counter[str] = Counter()
    for path in paths:
        assert check_sgd_domain(engine, path, 3, seen, PREFIXES) >= 5 * PREFIXES, path
    assert seen["allowed"] and seen["refused"] and seen["history broken"], seen


@pytest.mark.timeout(3600)
@pytest.mark.parametrize("domain", ["tau-airline", "tau-retail"])
def test_the_development_tau_calls(engine: Engine, domain: str) -> None:
    data = DataSettings().root / domain
    if not (data / "trajectories.json").exists():
        pytest.skip(f"the development data is not here ({data}; PRECOND_DATA_DIR)")
    seen: Counter[str] = Counter()
    check_tau(engine, data, CLAUSE if domain == "tau-airline" else {}, False, seen, DEVELOPMENT_RUNS)
    assert seen["allowed"] or seen["refused"], seen
