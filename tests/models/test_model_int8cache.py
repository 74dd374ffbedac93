"""The int8 weights kept on disk: the model they load is the one quantized in memory, and a cache that does not
verify is built again, never used."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import pytest
import torch
from torch import nn
from transformers import AutoModelForCausalLM

from precond.engine.models import int8cache
from precond.engine.models.quant import Int8Embedding, Int8Linear, quantize

pytestmark = pytest.mark.long  # collected first: pytest-xdist starts it first

KEY = "0123abcd-float32"


@pytest.fixture(params=["tied", "untied"])
def source(request: pytest.FixtureRequest, tiny_model_dir: Path, tmp_path: Path) -> Path:
    """The tiny checkpoint as a converted cache holds it; `untied`: its own vocabulary projection (as the
    embedded model's GGUF has), whose embedding the cache maps from its file instead of reading it."""
    directory = tmp_path / KEY
    if request.param == "tied":
        shutil.copytree(tiny_model_dir, directory)
        return directory
    model = AutoModelForCausalLM.from_pretrained(tiny_model_dir, dtype=torch.float32)
    model.config.tie_word_embeddings = False
    model.lm_head.weight = nn.Parameter(model.lm_head.weight.detach().clone() * 0.5)
    model.save_pretrained(directory)
    for name in ("tokenizer.json", "tokenizer_config.json"):
        shutil.copy2(tiny_model_dir / name, directory / name)
    return directory


def in_memory(source: Path) -> nn.Module:
    model = AutoModelForCausalLM.from_pretrained(source, dtype=torch.float32)
    quantize(model)
    return model.eval()


def logits(model: nn.Module) -> torch.Tensor:
    ids = torch.tensor([[1, 5, 9, 2, 7, 7, 3], [4, 4, 8, 1, 0, 6, 2]])
    with torch.inference_mode():
        return model(input_ids=ids).logits  # type: ignore[no-any-return]


def test_the_cached_int8_model_is_the_one_quantized_in_memory(source: Path, tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    model, home = int8cache.load(source, cache, KEY, torch.float32)
    assert home == cache / f"{KEY}-int8v{int8cache.FORMAT}"
    assert not any(isinstance(m, nn.Linear) for m in model.modules())
    assert isinstance(model.get_input_embeddings(), Int8Embedding)
    assert isinstance(model.get_output_embeddings(), Int8Linear)
    output, embedding = model.get_output_embeddings(), model.get_input_embeddings()
    assert output.transposed == (output.qweight is not embedding.qweight)  # an untied projection: in x out
    assert torch.equal(logits(model.eval()), logits(in_memory(source)))
    again, _ = int8cache.load(source, cache, KEY, torch.float32)
    assert torch.equal(logits(again.eval()), logits(model))
    assert [p.name for p in cache.iterdir()] == [home.name]  # no scratch directory left behind


def test_a_tied_vocabulary_projection_shares_the_embeddings_int8_rows(tiny_model_dir: Path, tmp_path: Path) -> None:
    shutil.copytree(tiny_model_dir, tmp_path / KEY)
    model, _ = int8cache.load(tmp_path / KEY, tmp_path / "cache", KEY, torch.float32)
    assert model.get_output_embeddings().qweight is model.get_input_embeddings().qweight


@pytest.mark.parametrize("damage", ["flip a byte", "truncate", "other format", "other source"])
def test_a_cache_that_does_not_verify_is_built_again(
    damage: str, source: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    cache = tmp_path / "cache"
    first, home = int8cache.load(source, cache, KEY, torch.float32)
    expected = logits(first.eval())
    weights, manifest = home / int8cache.WEIGHTS, home / int8cache.MANIFEST
    data = bytearray(weights.read_bytes())
    written = json.loads(manifest.read_text())
    if damage == "flip a byte":
        data[-5] ^= 0xFF
        weights.write_bytes(bytes(data))
    elif damage == "truncate":
        weights.write_bytes(bytes(data[:-64]))
    else:
        manifest.write_text(json.dumps({**written, **({"format": 0} if damage == "other format" else
                                                      {"source": "another-float32"})}))
    with caplog.at_level(logging.WARNING):
        model, _ = int8cache.load(source, cache, KEY, torch.float32)
    assert "do not match their manifest: building them again" in caplog.text
    assert torch.equal(logits(model.eval()), expected)
    assert json.loads(manifest.read_text()) == written
