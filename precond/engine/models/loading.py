"""Building models one at a time, and checking what was built.

transformers builds a model under process-wide state (whether new weights are initialised, which tied weights
are pending): two models built at once in two threads of one process can come out with the output layer that
should share the embedding's weights never loaded, left on the `meta` device or freshly random. Measured with
transformers 5.24 and the tiny test model: two threads loading at once gave an untied, `meta` `lm_head` in 3 of
5 tries, and a worker that preloads its serving model while a training job loads its own weights trained on
that random layer (a loss of NaN) or failed to quantize it. Every model this process builds is therefore built
under `one_at_a_time`, and a model loaded from a checkpoint is checked (`check_built`) before it is used:
a model that is not whole is refused with the reason, never served or trained.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from precond.engine.models.store import ModelStoreError

_BUILDING = threading.RLock()


@contextmanager
def one_at_a_time() -> Iterator[None]:
    """Hold while a model is built from a checkpoint or a config (re-entrant: a conversion inside a load)."""
    with _BUILDING:
        yield


def check_built(model: Any, source: object) -> None:
    """Raise ModelStoreError where `model` has a weight that was never loaded or an output layer its config ties
    to the embedding but that holds weights of its own."""
    unset = [name for name, tensor in [*model.named_parameters(), *model.named_buffers()] if tensor.is_meta]
    if unset:
        raise ModelStoreError(f"the model of {source} was built with {unset[:3]} never loaded")
    if not getattr(model.config, "tie_word_embeddings", False):
        return
    output, embedding = model.get_output_embeddings(), model.get_input_embeddings()
    if output is not None and output.weight is not embedding.weight:
        raise ModelStoreError(f"the model of {source} ties its output layer to the embedding, but they were "
                              "built apart")
