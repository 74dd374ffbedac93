"""Models built in several threads of one process at once (a worker preloads its serving model while a training
job loads its own weights) come out whole: every weight loaded, a tied output layer tied; and a model that is
not whole is refused, never served or trained."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from precond.engine.acting.training import train_policy
from precond.engine.models.loading import check_built
from precond.engine.models.store import ModelStoreError
from precond.engine.models.weights import Weights, load_weights
from precond.engine.settings import ModelSettings
from precond.engine.spec import parse_spec
from precond.stack.local import DEMOS, SPEC
from precond_client.schemas.errors import InvalidInput
from precond_client.schemas.training import TrainPolicyOptions, TrainPolicyRequest


def _settings(model_dir: Path) -> ModelSettings:
    return ModelSettings(path=str(model_dir), device="cpu", dtype="float32", threads=1, quant="none")


def test_models_loaded_in_threads_at_once_are_whole(tiny_model_dir: Path) -> None:
    """Without one build at a time, two threads gave an untied `lm_head` on `meta` in most rounds."""
    def load_into(loaded: list[Weights]) -> None:
        loaded.append(load_weights(_settings(tiny_model_dir)))

    for _ in range(4):
        loaded: list[Weights] = []
        threads = [threading.Thread(target=load_into, args=(loaded,)) for _ in range(3)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert len(loaded) == 3
        for weights in loaded:
            model = weights.model
            assert not any(p.is_meta for p in model.parameters())
            assert model.lm_head.weight is model.model.embed_tokens.weight


def test_an_untied_or_unloaded_model_is_refused(tiny_model_dir: Path) -> None:
    model = load_weights(_settings(tiny_model_dir)).model
    check_built(model, tiny_model_dir)
    model.lm_head.weight = torch.nn.Parameter(model.lm_head.weight.detach().clone())
    with pytest.raises(ModelStoreError, match="ties its output layer"):
        check_built(model, tiny_model_dir)
    model.lm_head.weight = torch.nn.Parameter(torch.empty_like(model.lm_head.weight, device="meta"))
    with pytest.raises(ModelStoreError, match="never loaded"):
        check_built(model, tiny_model_dir)


def test_a_training_whose_loss_is_not_finite_saves_nothing_and_says_so(tiny_model_dir: Path,
                                                                      tmp_path: Path) -> None:
    broken = tmp_path / "broken"
    broken.mkdir()
    for item in tiny_model_dir.iterdir():
        (broken / item.name).write_bytes(item.read_bytes())
    tensors = load_file(broken / "model.safetensors")
    name = next(k for k in tensors if k.endswith("mlp.down_proj.weight"))
    tensors[name] = torch.full_like(tensors[name], float("nan"))
    save_file(tensors, broken / "model.safetensors", metadata={"format": "pt"})
    request = TrainPolicyRequest(spec=SPEC, demonstrations=DEMOS[:2],
                                 options=TrainPolicyOptions(steps=2, max_tokens=1024))
    out = tmp_path / "adapter"
    with pytest.raises(InvalidInput, match="the loss at step 1 is nan") as refused:
        train_policy(lambda: load_weights(_settings(broken)), parse_spec(SPEC), request, out,
                     lambda *_: None, lambda: False)
    assert refused.value.field == "options.learning_rate"
    assert not out.exists()
