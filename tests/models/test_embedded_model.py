"""The real embedded Qwen2.5-Coder-0.5B: ~3 s with a warm cache, ~1 min the first time (it converts)."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import pytest
import torch

from precond.engine.models import CodeModel, ModelSettings, Sampling, load_code_model
from precond.engine.models.quant import QuantUnavailable, choose_quant
from precond.engine.models.store import EMBEDDED_SHA256, find_embedded_parts, join_parts
from precond.engine.models.weights import _weights_dir, cpu_dtype, cpu_flags

pytestmark = pytest.mark.model

SGD = Path(__file__).resolve().parents[1] / "fixtures" / "data" / "sgd" / "Restaurants_1.json"


def embedded_cache_dir() -> Path:
    return ModelSettings().cache_dir


@pytest.fixture(scope="module")
def embedded() -> CodeModel:
    return load_code_model(ModelSettings(device="cpu", threads=1, cache_dir=embedded_cache_dir()))


def sgd_prompt() -> str:
    """Observation class, one demonstration, then the USER class again to be annotated with assertions."""
    data = json.loads(SGD.read_text())
    spec = data["spec_program"]
    user_class = spec[: spec.index("class SYSTEM")]
    return f"{user_class}\n# Demonstration\n{data['demos'][0]['program']}\n# Preconditions\nclass USER:\n"


def test_greedy_assertion_parses(embedded: CodeModel) -> None:
    suffixes = ["  def INFORM(self, slot):\n    assert", "  def SELECT(self):\n    assert"]
    result = embedded.complete(sgd_prompt(), suffixes, 1, Sampling(temperature=0), "statement")
    for (text,) in result:
        assert text.strip()
        ast.parse("assert " + text)


def test_samples_mostly_parse(embedded: CodeModel) -> None:
    (texts,) = embedded.complete(
        sgd_prompt(), ["  def INFORM(self, slot):\n    assert"], 6, Sampling(seed=3), "statement"
    )
    parsed = 0
    for text in texts:
        try:
            ast.parse("assert " + text)
            parsed += 1
        except SyntaxError:
            pass
    assert len(texts) == 6 and parsed >= 4


def test_model_info(embedded: CodeModel) -> None:
    assert embedded.info.sha256 == EMBEDDED_SHA256
    dtype, reason = cpu_dtype(cpu_flags(), torch.backends.cpu.get_cpu_capability())
    assert (embedded.info.device, embedded.info.dtype) == ("cpu", str(dtype).removeprefix("torch."))
    assert embedded.info.dtype_reason == reason
    quant = choose_quant("auto", torch.device("cpu"), cpu_flags())
    assert (embedded.info.quant, embedded.info.quant_reason) == quant  # int8 where the CPU has VNNI


def test_int8_and_full_width_weights_greedily_write_the_same_assertions(embedded: CodeModel) -> None:
    """The accuracy check in small of the int8 weights `auto` serves (docs/model-speed.md has the evaluation): the
    greedy rules of two actions, against full width in the same dtype. Where `auto` keeps full width (no int8 dot
    products: emulated int8 is slower there, and only an explicit setting runs it) there is no default to check."""
    if embedded.info.quant != "int8":
        pytest.skip(f"int8 weights are not what this machine serves: {embedded.info.quant_reason}")
    try:
        second = load_code_model(ModelSettings(device="cpu", threads=1, quant="none", cache_dir=embedded_cache_dir()))
    except QuantUnavailable as exc:
        pytest.skip(str(exc))
    suffixes = ["  def INFORM(self, slot):\n    assert", "  def SELECT(self):\n    assert"]
    greedy = Sampling(temperature=0, max_new_tokens=24)

    def conditions(model: CodeModel) -> list[str]:  # the assertion's message may differ; the rule may not
        texts = [text for (text,) in model.complete(sgd_prompt(), suffixes, 1, greedy, "statement")]
        return [ast.dump(ast.parse("assert " + text).body[0].test) for text in texts]  # type: ignore[attr-defined]

    assert conditions(embedded) == conditions(second)


def test_gguf_path_is_converted_once_by_hash(embedded: CodeModel, tmp_path: Path) -> None:
    """A configured .gguf file is keyed by its sha256: the embedded file's bytes hit the embedded cache (the
    directory the loaded embedded model came from), and nothing is converted again."""
    gguf_file = tmp_path / "qwen-coder.gguf"
    join_parts(find_embedded_parts(), gguf_file, EMBEDDED_SHA256)
    cache = embedded_cache_dir()
    before = sorted(cache.iterdir())
    settings = ModelSettings(path=str(gguf_file), device="cpu", cache_dir=cache)
    directory, name, sha256 = _weights_dir(settings, embedded.info.dtype)
    assert (name, sha256) == ("qwen-coder", EMBEDDED_SHA256)
    assert directory == _weights_dir(ModelSettings(cache_dir=cache), embedded.info.dtype)[0]
    assert sorted(cache.iterdir()) == before
