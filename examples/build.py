"""Write the request bodies in examples/ from the shared SGD Restaurants_1 data (no ground-truth fields).

python examples/build.py [PATH]   # default: sgd/Restaurants_1.json of PRECOND_DATA_DIR (../shared/data)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
# Hand-written, in the shape /infer-preconditions returns: an example, not the data set's ground truth.
PRECONDITIONS = {
    "SYSTEM.FindRestaurants": ["self.user.informed_slot['city']", "self.user.informed_slot['cuisine']"],
    "SYSTEM.INFORM": ["self.user.requested_slot[slot]"],
}


def bodies(domain: dict[str, object]) -> dict[str, dict[str, object]]:
    spec = str(domain["spec_program"])
    demos = [str(d["program"]) for d in domain["demos"][:2]]  # type: ignore[index]
    history = "\n".join(str(domain["test"][0]["program"]).splitlines()[:7]) + "\n"  # type: ignore[index]
    return {
        # two demonstrations are too few for evidence-weighted validation (an action seen fewer than three
        # times learns nothing): these examples ask for the paper's strict validation, `tolerance: 0`
        "infer-enumerate": {"spec": spec, "demonstrations": demos,
                            "options": {"generators": ["enumerate"], "tolerance": 0}},
        # the same, answering with the kept rules' reports only (19 KB instead of 490 KB): what serve.sh shows
        "infer-kept": {"spec": spec, "demonstrations": demos,
                       "options": {"generators": ["enumerate"], "tolerance": 0, "candidates": "kept"}},
        "infer-model": {
            "spec": spec,
            "demonstrations": demos,
            "actions": ["SYSTEM.FindRestaurants", "SYSTEM.INFORM"],
            "options": {
                "generators": ["model", "enumerate"],
                "samples_per_prompt": 4,
                "prompts_per_action": 2,
                "tolerance": 0,
            },
        },
        "next-action": {
            "spec": spec,
            "preconditions": PRECONDITIONS,
            "demonstrations": demos[:1],
            "history": history,
        },
        "check-actions": {
            "spec": spec,
            "preconditions": PRECONDITIONS,
            "history": history,
            "calls": ["system.FindRestaurants()", "system.INFORM('phone_number')"],
        },
    }


def main(source: Path) -> None:
    domain = json.loads(source.read_text())
    for name, body in bodies(domain).items():
        (HERE / f"{name}.json").write_text(json.dumps(body, indent=2) + "\n")


if __name__ == "__main__":
    if len(sys.argv) > 1:
        main(Path(sys.argv[1]))
    else:
        sys.path.insert(0, str(HERE.parent))
        from precond.evaluation.settings import data_path

        main(data_path("sgd", "Restaurants_1.json"))
