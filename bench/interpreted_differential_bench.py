"""The gateway's interpreter against the sandbox on every prefix of every development SGD domain: the full sweep
that tests/service/test_interpreted_differential_development.py samples (a dozen prefixes a domain).

    python bench/interpreted_differential_bench.py [--data ../shared/data/sgd] [--dialogs 3] [--json out.json]

Every domain under every condition the enumerator proposes for it, its learned rules and the hand-written ones,
each judged by both after every prefix (before a system call) of its first `--dialogs` dialogs, as the test
compares them (every field equal but `judged_by`). A difference stops the run with the case that differs (exit
1). Reported: the checks compared a domain and in all, the verdicts seen by kind and the wall-clock seconds (on a
shared machine, the other processes' time is in them).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from precond.engine.engine import Engine  # noqa: E402
from precond.evaluation.settings import DataSettings  # noqa: E402
from precond.sandbox import Sandbox  # noqa: E402
from precond.stack.differential import check_sgd_domain  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DataSettings().root / "sgd")
    parser.add_argument("--dialogs", type=int, default=3)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    paths = sorted(args.data.glob("*_*.json"))
    if not paths:
        sys.exit(f"no SGD domain in {args.data}")
    seen: Counter[str] = Counter()
    checks: dict[str, int] = {}
    started = time.perf_counter()
    with Sandbox(workers=2) as sandbox:
        engine = Engine(sandbox, None)
        for path in paths:
            checks[path.stem] = check_sgd_domain(engine, path, args.dialogs, seen)
    results = {"domains": len(paths), "checks": sum(checks.values()), "checks_per_domain": checks,
               "verdicts": dict(seen), "seconds": round(time.perf_counter() - started, 1)}
    print(json.dumps(results, indent=1))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
