"""`MODEL_QUANT`: which weights a machine gets, the refusals, and an int8 model that answers like the full one."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from pydantic import ValidationError
from torch import nn

from precond.engine.models import ModelSettings, Sampling, load_code_model
from precond.engine.models import weights as weights_module
from precond.engine.models.quant import Int8Embedding, Int8Linear, QuantUnavailable, choose_quant

CPU = torch.device("cpu")
VNNI = frozenset({"avx2", "avx512f", "avx512_vnni"})
PREFIX = "class USER:\n  def __init__(self):\n    self.informed_slot = defaultdict(lambda: False)\n" * 4
SUFFIXES = ["  def INFORM(self, slot):\n    assert", "  def SELECT(self):\n    assert"]


def test_an_unknown_quantization_is_refused_when_the_settings_are_read(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MODEL_QUANT", "int4")
    with pytest.raises(ValidationError, match="MODEL_QUANT='int4' is not one of auto, none, int8"):
        ModelSettings()


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        (VNNI, ("int8", "int8 weights: cpu with avx512_vnni")),
        (frozenset({"avx2", "avx_vnni"}), ("int8", "int8 weights: cpu with avx_vnni")),
        (frozenset({"avx2", "avx512f"}), ("none", "no int8 weights: cpu without amx_int8/avx512_vnni/avx_vnni")),
        (frozenset({"sse4_2"}), ("none", "no int8 weights: cpu without avx2 (the int8 kernels need it)")),
        (None, ("none", "no int8 weights: cpu features unknown (no /proc/cpuinfo), so avx2 cannot be checked")),
    ],
)
def test_auto_quantizes_only_where_the_cpu_has_int8_dot_products(
    flags: frozenset[str] | None, expected: tuple[str, str]
) -> None:
    assert choose_quant("auto", CPU, flags) == expected


def test_explicit_settings_are_followed_or_refused_naming_the_setting_and_the_flag() -> None:
    assert choose_quant("none", CPU, VNNI) == ("none", "MODEL_QUANT=none")
    assert choose_quant("int8", CPU, VNNI) == ("int8", "MODEL_QUANT=int8")
    with pytest.raises(QuantUnavailable, match=r"MODEL_QUANT=int8 cannot run here: cpu without avx2"):
        choose_quant("int8", CPU, frozenset({"sse4_2"}))
    with pytest.raises(QuantUnavailable, match=r"MODEL_QUANT=int8 cannot run here: .* runs on cuda"):
        choose_quant("int8", torch.device("cuda"), VNNI)
    assert choose_quant("auto", torch.device("cuda"), VNNI)[0] == "none"


def test_int8_asked_for_on_a_cpu_without_int8_dot_products_runs_and_says_it_is_slow(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Emulated int8 products are many times slower than float32 (bench/kernel_bench.py on an AVX2 EPYC): the
    explicit setting is followed, for its memory, never silently: the reason every answer carries and a warning
    name the missing flags."""
    with caplog.at_level("WARNING", logger="precond.engine.models.quant"):
        quant, reason = choose_quant("int8", CPU, frozenset({"avx2", "fma"}))
    assert quant == "int8"
    assert reason == ("MODEL_QUANT=int8 on a cpu without amx_int8/avx512_vnni/avx_vnni: int8 products are "
                      "emulated, slower than full-width weights here")
    assert [record.getMessage() for record in caplog.records] == [reason]


def test_a_worker_asked_for_int8_on_a_cpu_without_it_fails_its_load(
    tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No silent full-width model: the load (at worker start with PRECOND_PRELOAD_MODEL) raises, and says why."""
    monkeypatch.setattr(weights_module, "cpu_flags", lambda: frozenset({"sse4_2"}))
    settings = ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="int8")
    with pytest.raises(QuantUnavailable, match=r"MODEL_QUANT=int8 .* avx2"):
        load_code_model(settings)


def test_an_int8_models_rows_do_not_depend_on_their_batch(tiny_model_dir: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(weights_module, "cpu_flags", lambda: VNNI)
    small = load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="int8"))
    first = small.tokenizer(PREFIX[:60], return_tensors="pt")["input_ids"]
    ids = torch.cat([first, first.flip(1) * 3 % small.model.config.vocab_size])  # another row, other magnitudes
    with torch.inference_mode():
        together = small.model(input_ids=ids).logits
        alone = small.model(input_ids=ids[:1]).logits
    assert torch.equal(together[:1], alone)


def test_an_int8_model_keeps_the_full_models_choices(tiny_model_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(weights_module, "cpu_flags", lambda: VNNI)
    full = load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="none"))
    small = load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="int8"))
    assert (small.info.quant, small.info.quant_reason) == ("int8", "MODEL_QUANT=int8")
    assert (full.info.quant, full.info.quant_reason) == ("none", "MODEL_QUANT=none")
    assert not any(isinstance(m, nn.Linear) for m in small.model.modules())
    assert any(isinstance(m, Int8Linear) for m in small.model.modules())
    assert isinstance(small.model.get_input_embeddings(), Int8Embedding)
    continuations = [" slot in self.informed_slot", " True", " self.informed_slot[slot]", " False"]
    full_scores = full.score(PREFIX, continuations)
    small_scores = small.score(PREFIX, continuations)
    assert small_scores == pytest.approx(full_scores, rel=0.05)
    texts = small.complete(PREFIX, SUFFIXES, 2, Sampling(max_new_tokens=8), "line")
    assert [len(t) for t in texts] == [2, 2]


def _resident_kb(path: Path) -> int:
    """Resident kB of this process's mappings of `path` (/proc/self/smaps)."""
    total, inside = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        if "-" in line.split(" ", 1)[0]:
            inside = line.endswith(str(path))
        elif inside and line.startswith("Rss:"):
            total += int(line.split()[1])
    return total


@pytest.mark.skipif(not Path("/proc/self/smaps").is_file(), reason="reads Linux's /proc/self/smaps")
def test_a_mapped_embedding_looks_up_the_same_rows_and_leaves_none_resident(tmp_path: Path) -> None:
    rows = torch.randint(-127, 128, (2048, 512), dtype=torch.int8)
    path = tmp_path / "rows.bin"
    path.write_bytes(rows.numpy().tobytes())
    mapped = torch.from_file(str(path), shared=False, size=rows.numel(), dtype=torch.int8).view(rows.shape)
    scales = torch.rand(rows.shape[0])
    ids = torch.tensor([[3, 700, 2047, 3], [0, 1500, 9, 1024]])
    expected = Int8Embedding(rows, scales, torch.bfloat16)(ids)
    assert int(mapped.sum()) == int(rows.sum()) and _resident_kb(path) >= rows.numel() // 1024
    embedding = Int8Embedding(mapped, scales, torch.bfloat16, mapped=True)
    assert torch.equal(embedding(ids), expected)
    assert _resident_kb(path) == 0
    assert torch.equal(embedding(ids), expected)  # mapped again from the file


def test_an_int8_layer_multiplies_exactly_and_rounds_once_per_scale() -> None:
    generator = torch.Generator().manual_seed(0)
    linear = nn.Linear(64, 300, bias=True)
    layer = Int8Linear.of(linear, transposed=False)
    x = torch.randn(5, 64, generator=generator)
    row_scales = x.abs().amax(dim=1, keepdim=True).clamp(min=1e-12) / 127.0
    exact = torch.round(x / row_scales).long() @ layer.qweight.long().t()  # no int32 wrap-around or reordering
    expected = exact.float() * row_scales * layer.scales + linear.bias.detach()
    assert torch.equal(layer(x), expected)
