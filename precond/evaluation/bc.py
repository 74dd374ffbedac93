"""The BC rows of `precond eval next-action`: one adapter per domain, trained on its ten demonstrations only.

An adapter is kept in the evaluation cache under a key of everything that trained it (the spec, the
demonstrations, the options, the base model), so a second run reuses it and a change retrains. Training uses
every core (`os.cpu_count()` threads), then restores the thread count the evaluation's latency was measured with.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch

from precond.engine.acting.training import OBJECTIVE, train_policy
from precond.engine.models.adapters import RESULT, read_result
from precond.engine.models.weights import load_weights
from precond.engine.settings import ModelSettings
from precond.engine.spec import parse_spec
from precond.evaluation.domains import Domain
from precond_client.schemas.training import TrainPolicyOptions, TrainPolicyRequest, TrainPolicyResult


def request_of(domain: Domain, options: TrainPolicyOptions) -> TrainPolicyRequest:
    return TrainPolicyRequest(spec=domain.spec, demonstrations=list(domain.demonstrations), options=options)


def adapter_dir(root: Path, domain: Domain, options: TrainPolicyOptions, settings: ModelSettings) -> Path:
    body = request_of(domain, options).model_dump_json() + json.dumps([settings.path, settings.dtype, OBJECTIVE])
    return root / "adapters" / domain.name / hashlib.sha256(body.encode()).hexdigest()[:16]


DEFAULTS = TrainPolicyOptions()


def trained(root: Path, domain: Domain, options: TrainPolicyOptions = DEFAULTS) -> tuple[Path, TrainPolicyResult]:
    """The domain's adapter, trained now if the cache has none."""
    settings = ModelSettings(threads=os.cpu_count() or 1)
    directory = adapter_dir(root, domain, options, settings)
    if (directory / RESULT).is_file():
        return directory, read_result(directory)
    threads = torch.get_num_threads()
    try:
        request = request_of(domain, options)
        result = train_policy(lambda: load_weights(settings), parse_spec(request.spec), request, directory,
                              lambda *_: None, lambda: False)
    finally:
        torch.set_num_threads(threads)
    return directory, result
