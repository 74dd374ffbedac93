"""What prior rules add to an inference's time: the SGD dev domains, model-free (`enumerate`, cautious), each
inferred without priors and with the other domains' inferred rules as priors (leave one domain out, as
`precond eval transfer`), alternating, best of `--repeat` runs each (the slowest runs on a shared machine
measure the neighbours). The model's generation is the same with or without priors (priors never enter a
prompt), so the model-free inference is where their cost shows.

    python bench/priors_bench.py [--repeat 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from precond.engine.engine import Engine
from precond.evaluation.domains import load_domains
from precond.evaluation.settings import DataSettings
from precond.sandbox import Sandbox
from precond_client.schemas import InferOptions, InferRequest, PriorSource


def _seconds(engine: Engine, request: InferRequest) -> float:
    start = time.perf_counter()
    engine.infer(request)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    domains = load_domains(DataSettings().path("sgd"))
    rows = []
    with Sandbox(workers=2) as sandbox:
        engine = Engine(sandbox, None)
        requests = {d.name: InferRequest(spec=d.spec, demonstrations=list(d.demonstrations), actions=list(d.actions),
                                         options=InferOptions(generators=["enumerate"])) for d in domains}
        rules = {name: engine.infer(r).preconditions for name, r in requests.items()}
        for name, request in requests.items():
            sources = [PriorSource(source=other, rules=r) for other, r in rules.items() if other != name]
            primed = request.model_copy(update={"options": request.options.model_copy(
                update={"prior_sources": sources})})
            alone, with_priors = [], []
            for _ in range(args.repeat):
                alone.append(_seconds(engine, request))
                with_priors.append(_seconds(engine, primed))
            rows.append((name, min(alone), min(with_priors)))
            print(f"{name}: without {min(alone):.3f} s, with priors {min(with_priors):.3f} s "
                  f"({min(with_priors) / min(alone) - 1:+.1%})")
    total = sum(r[2] for r in rows) / sum(r[1] for r in rows) - 1
    print(f"all domains: {total:+.1%}")
    if args.json:
        table = [{"domain": d, "without_s": without, "with_s": with_} for d, without, with_ in rows]
        args.json.write_text(json.dumps({"rows": table, "added": total}, indent=1))


if __name__ == "__main__":
    main()
