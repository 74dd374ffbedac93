"""Results from separate runs merge; a failed re-run never hides an earlier measurement."""

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
