"""Results from separate runs merge; a failed re-run never hides an earlier measurement; the sized next-action table."""

from __future__ import annotations

from pathlib import Path

from evaluation.cache import JsonCache
from evaluation.report import main_table, store_precondition_results

GOOD = {"config": "model/recency", "domain": "Buses_1", "benchmark": "sgd", "error": None,
        "macro": {"precision": 0.9, "recall": 0.5, "f1": 0.6}}
FAILED = {"config": "model/recency", "domain": "Buses_1", "benchmark": "sgd", "error": "model_unavailable: no"}


def test_failed_rerun_keeps_the_measurement(tmp_path: Path) -> None:
    store = JsonCache(tmp_path)
    store_precondition_results(store, {"rows": [GOOD]})
    store_precondition_results(store, {"rows": [FAILED]})
    rows = store.get("results", "preconditions")["rows"]
    assert rows == [GOOD]
    assert "| `model/recency` | 0.900 | 0.500 | 0.600 |" in main_table(rows)


def test_sized_run_is_a_table_with_intervals_and_a_plot(tmp_path: Path) -> None:
    from evaluation.plots import sized_plot
    from evaluation.report import sized_table
    from evaluation.sized import summarize

    row = {"turn": 1, "reference": ["x()"], "seconds": 1.0, "domain": "D"}
    results = {"base": [row | {"dialog": d, "predicted": ["y()"], "compatible": [False]} for d in "abc"],
               "mode": [row | {"dialog": d, "predicted": ["x()"], "compatible": [True]} for d in "abc"]}
    rows = summarize(results, "base")
    table = sized_table({"rows": rows})
    assert "| `mode` | 3 | 3 | 1.000 [1.000, 1.000] | 1.000 [1.000, 1.000] (n=3) | +1.000 [+1.000, +1.000]" in table
    plot = sized_plot(rows, tmp_path)
    assert plot is not None and plot.stat().st_size > 0
