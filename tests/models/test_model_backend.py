from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch
from layouts import TOLERANCE, in_two_layouts, recorded, replayed
from pydantic import ValidationError
from transformers import DynamicCache

from precond.engine.models import GenerationCancelled, ModelSettings, Sampling, load_code_model
from precond.engine.models.backend import PREFILL_CHUNK, WIDE_ROWS, CodeModel, sample_next
from precond.engine.models.prefixes import Prefix, PrefixStore
from precond.engine.models.stopping import StopRule, statement_end, stop_index
from precond.engine.models.weights import choose_dtype, cpu_dtype, cpu_flags
from precond.engine.scope import scoped

pytestmark = pytest.mark.long  # collected first: pytest-xdist starts it first

PREFIX = "class USER:\n  def __init__(self):\n    self.informed_slot = defaultdict(lambda: False)\n" * 12
SUFFIXES = ["  def INFORM(self, slot):\n    assert", "  def SELECT(self):\n    assert", "user = USER()\n"]


@pytest.fixture(scope="module")
def tiny(tiny_model_dir: Path) -> CodeModel:
    """The tiny model in float32 with float32 weights on every CPU: `quant` auto would serve int8 weights on a CPU
    with avx512_vnni, where each layer rounds its input rows to int8 and a last-bit difference between two layouts
    becomes a whole int8 step (up to 0.14 in a logit between the shared-prefix and the copied layout); these tests
    compare layouts (tests/models/test_model_quant.py tests int8)."""
    settings = ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="none", max_batch=4)
    return load_code_model(settings)


def reference_greedy(model: CodeModel, text: str, max_new_tokens: int, stop: StopRule) -> str:
    """Plain greedy decoding of the whole prompt, recomputed from scratch at every step (no cache at all)."""
    ids = model.tokenizer(text)["input_ids"]
    generated: list[int] = []
    for _ in range(max_new_tokens):
        with torch.inference_mode():
            logits = model.model(input_ids=torch.tensor([ids + generated])).logits[0, -1]
        token = int(logits.argmax())
        if token in model._stop_ids:
            break
        generated.append(token)
    decoded = model.tokenizer.decode(generated)
    cut = stop_index(decoded, stop)
    return decoded if cut is None else decoded[:cut]


def test_prefix_is_longer_than_one_prefill_chunk(tiny: CodeModel) -> None:
    assert len(tiny.tokenizer(PREFIX)["input_ids"]) > 2 * PREFILL_CHUNK


def test_n_completions_per_suffix(tiny: CodeModel) -> None:
    result = tiny.complete(PREFIX, SUFFIXES, 5, Sampling(max_new_tokens=8), "line")
    assert [len(completions) for completions in result] == [5, 5, 5]
    assert all(isinstance(text, str) and "\n" not in text for texts in result for text in texts)


def test_same_seed_same_samples(tiny: CodeModel) -> None:
    sampling = Sampling(max_new_tokens=12, seed=7)
    first = tiny.complete(PREFIX, SUFFIXES, 3, sampling, "statement")
    tiny.complete("other prefix\n", SUFFIXES[:1], 2, Sampling(seed=1), "line")  # disturbs the kept cache
    assert tiny.complete(PREFIX, SUFFIXES, 3, sampling, "statement") == first
    assert tiny.complete(PREFIX, SUFFIXES, 3, Sampling(max_new_tokens=12, seed=8), "statement") != first


@pytest.mark.parametrize("max_batch", [2, 32])
def test_a_prompts_samples_do_not_depend_on_what_is_sampled_beside_it(tiny: CodeModel, max_batch: int,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Each row draws its own random numbers (seed, suffix, sample index, step): asking about fewer actions,
    or running another `max_batch`, changes nobody's samples (`options.model_for`, MODEL_MAX_BATCH): given the
    same tokens, its logits are the same within `layouts.TOLERANCE` (the layouts' sums may differ in their last
    bits, enough to move a sample of the tiny model's nearly flat distribution)."""
    sampling = Sampling(max_new_tokens=12, seed=3)
    other = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=max_batch)
    together, alone = in_two_layouts(monkeypatch, lambda: tiny.complete(PREFIX, SUFFIXES, 4, sampling, "statement"),
                                     lambda: other.complete(PREFIX, SUFFIXES[1:2], 4, sampling, "statement"))
    assert alone == together[1:2]
    assert len(set(together[1])) > 1  # the samples of one prompt still differ from each other


def test_greedy_forces_one_sample(tiny: CodeModel) -> None:
    sampling = Sampling(temperature=0, max_new_tokens=10)
    result = tiny.complete(PREFIX, SUFFIXES, 4, sampling, "statement")
    assert [len(completions) for completions in result] == [1, 1, 1]
    assert tiny.complete(PREFIX, SUFFIXES, 4, sampling, "statement") == result


@pytest.mark.parametrize("stop", ["line", "statement"])
def test_cached_prefix_matches_plain_greedy_decode(tiny: CodeModel, stop: StopRule) -> None:
    sampling = Sampling(temperature=0, max_new_tokens=24)
    expected = [[reference_greedy(tiny, PREFIX + suffix, 24, stop)] for suffix in SUFFIXES]
    assert tiny.complete(PREFIX, SUFFIXES, 1, sampling, stop) == expected
    # Per-suffix calls reuse the kept prefix cache (cropped to a chunk boundary) and must agree too.
    assert [tiny.complete(PREFIX, [suffix], 1, sampling, stop)[0] for suffix in SUFFIXES] == expected


def test_empty_prefix_with_unequal_suffixes(tiny: CodeModel) -> None:
    """Nothing shared: pad positions have no prefix to attend to, which must not poison the batch."""
    suffixes = ["def f(x", "class USER:\n  def __init__(self):\n"]
    sampling = Sampling(temperature=0, max_new_tokens=16)
    expected = [[reference_greedy(tiny, suffix, 16, "line")] for suffix in suffixes]
    assert tiny.complete("", suffixes, 1, sampling, "line") == expected


def test_token_budget_bounds_the_output(tiny: CodeModel) -> None:
    sampling = Sampling(temperature=0, max_new_tokens=2)
    expected = [[reference_greedy(tiny, PREFIX + suffix, 2, "statement")] for suffix in SUFFIXES]
    assert tiny.complete(PREFIX, SUFFIXES, 1, sampling, "statement") == expected


def test_sampled_statements_are_cut_at_their_end(tiny: CodeModel) -> None:
    result = tiny.complete(PREFIX, SUFFIXES, 6, Sampling(temperature=1.5, max_new_tokens=32), "statement")
    assert all(statement_end(text) is None for texts in result for text in texts)


def test_cancellation_between_steps(tiny: CodeModel) -> None:
    calls: list[int] = []

    def should_stop() -> bool:
        calls.append(1)
        return len(calls) > 2

    with pytest.raises(GenerationCancelled):
        tiny.complete(PREFIX, SUFFIXES, 2, Sampling(max_new_tokens=40), "statement", should_stop)


def test_no_suffixes_no_work(tiny: CodeModel) -> None:
    assert tiny.complete(PREFIX, [], 3, Sampling(), "line") == []


def test_model_info(tiny: CodeModel, tiny_model_dir: Path) -> None:
    assert tiny.info.name == tiny_model_dir.name
    assert (tiny.info.device, tiny.info.dtype, tiny.info.sha256) == ("cpu", "float32", None)


@pytest.mark.parametrize("max_batch", [1, 2])
def test_refilled_batches_match_plain_greedy_decode(tiny: CodeModel, max_batch: int) -> None:
    """Rows joining a running batch (other widths, padding in the middle) decode as if alone."""
    refilling = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=max_batch)
    sampling = Sampling(temperature=0, max_new_tokens=20)
    expected = [[reference_greedy(tiny, PREFIX + suffix, 20, "line")] for suffix in SUFFIXES]
    assert refilling.complete(PREFIX, SUFFIXES, 1, sampling, "line") == expected


def test_samples_do_not_depend_on_batch_size_for_greedy(tiny: CodeModel) -> None:
    sampling = Sampling(temperature=0, max_new_tokens=16)
    small = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=2)
    assert small.complete(PREFIX, SUFFIXES, 1, sampling, "statement") == tiny.complete(
        PREFIX, SUFFIXES, 1, sampling, "statement"
    )


@pytest.mark.parametrize("bad", [{"temperature": -1.0}, {"top_p": 0.0}, {"max_new_tokens": 0}])
def test_invalid_sampling_is_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="invalid sampling"):
        Sampling(**bad)  # type: ignore[arg-type]


def test_model_info_says_why_its_dtype(tiny: CodeModel) -> None:
    assert tiny.info.dtype_reason == "MODEL_DTYPE=float32: float32"


@pytest.mark.parametrize(
    ("flags", "capability", "expected"),
    [
        ("fpu avx2 avx512f", "AVX512", (torch.float32, "cpu without amx_bf16/avx512_bf16: float32")),
        ("fpu avx2", "AVX2", (torch.float32, "cpu without amx_bf16/avx512_bf16: float32")),
        ("avx512f avx512_bf16", "AVX512", (torch.bfloat16, "cpu with avx512_bf16: bfloat16")),
        ("amx_tile amx_bf16 avx512_bf16", "AVX512", (torch.bfloat16, "cpu with amx_bf16: bfloat16")),
        ("avx512f avx512_bf16", "AVX2", (torch.float32, "cpu has avx512_bf16 but torch runs AVX2 kernels: float32")),
    ],
)
def test_cpu_dtype_follows_native_bf16(flags: str, capability: str, expected: tuple[torch.dtype, str]) -> None:
    assert cpu_dtype(frozenset(flags.split()), capability) == expected


def test_cpu_flags_are_read_from_cpuinfo(tmp_path: Path) -> None:
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nflags\t\t: fpu avx2 avx512_bf16\n\nprocessor\t: 1\nflags\t\t: fpu\n")
    assert cpu_flags(cpuinfo) == frozenset({"fpu", "avx2", "avx512_bf16"})
    assert cpu_flags(tmp_path / "absent") is None
    assert cpu_dtype(None, "AVX512") == (torch.float32, "cpu features unknown (no /proc/cpuinfo): float32")


def test_explicit_dtype_overrides_detection() -> None:
    cpu = torch.device("cpu")
    assert choose_dtype("bf16", cpu) == (torch.bfloat16, "MODEL_DTYPE=bf16: bfloat16")
    assert choose_dtype("auto", cpu) == cpu_dtype(cpu_flags(), torch.backends.cpu.get_cpu_capability())
    with pytest.raises(ValueError, match="unknown dtype"):
        choose_dtype("int3", cpu)



def _common(a: list[int], b: list[int]) -> int:
    return next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))


class _Counting:
    """Counts the model's forward calls: decode steps apart, and the tokens every other call (a prefill of
    prefix chunks or of tails) computed; pads are not counted."""

    def __init__(self, model: CodeModel) -> None:
        self.model = model
        self.prefilled = self.prefill_calls = self.decode_calls = 0
        self._in_step = False

    def __enter__(self) -> _Counting:
        forward, step = self.model.model.forward, self.model._step

        def counted_forward(*args: Any, **kwargs: Any) -> Any:
            width = kwargs["input_ids"].shape[1]
            if self._in_step:
                self.decode_calls += 1
            else:
                self.prefill_calls += 1
                mask = kwargs["attention_mask"]
                # a 4D mask is a scored token tree: one row, no pads
                self.prefilled += width if mask.dim() == 4 else int(mask[:, -width:].sum())
            return forward(*args, **kwargs)

        def counted_step(*args: Any, **kwargs: Any) -> Any:
            self._in_step = True
            try:
                return step(*args, **kwargs)
            finally:
                self._in_step = False

        self.model.model.forward = counted_forward
        self.model._step = counted_step  # type: ignore[method-assign]
        return self

    def __exit__(self, *exc: object) -> None:
        del self.model.model.forward
        del self.model._step


@pytest.mark.parametrize("n", [1, 3, 8])
def test_n_samples_of_a_prompt_cost_one_prefill(tiny: CodeModel, n: int) -> None:
    """However many samples, and however often the batch (4 rows here) is refilled, the prompt runs once."""
    prompt_tokens = len(tiny.tokenizer(PREFIX + SUFFIXES[0])["input_ids"])
    fresh = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=4)
    with _Counting(fresh) as counting:
        (texts,) = fresh.complete(PREFIX, SUFFIXES[:1], n, Sampling(temperature=1.0, max_new_tokens=6), "line")
    assert len(texts) == n
    assert counting.prefilled == prompt_tokens
    assert counting.prefill_calls == -(-(prompt_tokens - 1) // PREFILL_CHUNK) + 1  # prefix chunks, the tail
    assert counting.decode_calls > 0


def test_prompts_sharing_a_prefix_prefill_it_once(tiny: CodeModel) -> None:
    """Three prompts x 5 samples over refills of 4 rows: the shared prefix once, each prompt's tail once; a
    later call with the same prefix (per-action calls of one spec) reuses the prefix's whole chunks."""
    ids = [tiny.tokenizer(PREFIX + suffix)["input_ids"] for suffix in SUFFIXES]
    shared = min(min(len(i) for i in ids) - 1, min(_common(ids[0], i) for i in ids))
    fresh = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=4)
    with _Counting(fresh) as counting:
        fresh.complete(PREFIX, SUFFIXES, 5, Sampling(max_new_tokens=4), "line")
    assert counting.prefilled == shared + sum(len(i) - shared for i in ids)

    with _Counting(fresh) as again:
        fresh.complete(PREFIX, SUFFIXES[1:2], 5, Sampling(max_new_tokens=4), "line")
    assert again.prefilled == len(ids[1]) - shared // PREFILL_CHUNK * PREFILL_CHUNK


def reference_score(model: CodeModel, prefix: str, continuation: str) -> float:
    """Log-likelihood of the continuation's tokens from one plain forward pass over the whole text (no cache)."""
    head = model.tokenizer(prefix)["input_ids"]
    ids = model.tokenizer(prefix + continuation)["input_ids"]
    start = max(1, _common(head, ids))
    with torch.inference_mode():
        logprobs = torch.log_softmax(model.model(input_ids=torch.tensor([ids])).logits[0].float(), dim=-1)
    return float(sum(logprobs[j - 1, ids[j]] for j in range(start, len(ids))))


CONTINUATIONS = [" self.informed_slot[slot]", " not self.informed_slot[slot]", " True", "\n"]


@pytest.mark.parametrize("max_nodes", [1, 6, 1024])
def test_scores_match_one_plain_forward_pass(tiny_model_dir: Path, max_nodes: int,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Whatever the trees' size (one continuation per pass, a few, all), the same log-likelihoods."""
    monkeypatch.setattr("precond.engine.models.backend.MAX_TREE_NODES", max_nodes)
    model = load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="none"))
    prefix = PREFIX + SUFFIXES[0]
    expected = [reference_score(model, prefix, text) for text in CONTINUATIONS]
    assert model.score(prefix, CONTINUATIONS) == pytest.approx(expected, abs=1e-3)
    assert model.score("", ["def f(x", "class USER:\n"]) == pytest.approx(
        [reference_score(model, "", "def f(x"), reference_score(model, "", "class USER:\n")], abs=1e-3
    )


def test_scoring_prefills_the_prefix_once(tiny: CodeModel) -> None:
    """The prompt's prefix runs once whatever the number of continuations; each token the continuations
    share runs once too (`self.informed_slot[slot]` inside `not self.informed_slot[slot]` does not)."""
    prefix = PREFIX + "\n# a new prompt\n"
    ids = [tiny.tokenizer(prefix + text)["input_ids"] for text in CONTINUATIONS]
    shared = min(_common(tiny.tokenizer(prefix)["input_ids"], i) for i in ids) - 1
    distinct = {tuple(i[: k + 1]) for i in ids for k in range(shared, len(i))}
    fresh = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=2)
    with _Counting(fresh) as counting:
        fresh.score(prefix, CONTINUATIONS)
    assert counting.prefilled == shared + len(distinct)
    with _Counting(fresh) as again:
        fresh.score(prefix, [*CONTINUATIONS, *CONTINUATIONS])
    assert again.prefilled == len(distinct)  # the prefix is kept; repeated continuations cost nothing more


def test_no_continuations_no_work(tiny: CodeModel) -> None:
    assert tiny.score(PREFIX, []) == []


def test_a_tenant_never_reuses_another_tenants_prefix(tiny: CodeModel) -> None:
    """The prompt-caching side channel: were B's identical prompt served from A's kept prefix, B's call would
    prefill only its tail and answer faster, telling B that somebody sent that text. Each scope computes its
    own; a scope's own later call reuses what it kept."""
    prompt_tokens = len(tiny.tokenizer(PREFIX + SUFFIXES[0])["input_ids"])
    fresh = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=4)
    sampling = Sampling(temperature=0, max_new_tokens=4)
    with scoped("tenant-a"):
        first = fresh.complete(PREFIX, SUFFIXES[:1], 1, sampling, "line")
    with scoped("tenant-b"), _Counting(fresh) as other:
        assert fresh.complete(PREFIX, SUFFIXES[:1], 1, sampling, "line") == first
    assert other.prefilled == prompt_tokens
    with scoped("tenant-a"), _Counting(fresh) as same:
        fresh.complete(PREFIX, SUFFIXES[:1], 1, sampling, "line")
    assert same.prefilled < prompt_tokens - PREFILL_CHUNK


def test_scores_are_scoped_too(tiny: CodeModel) -> None:
    fresh = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=4)
    with scoped("tenant-a"):
        fresh.score(PREFIX, CONTINUATIONS)
    with scoped("tenant-b"), _Counting(fresh) as other:
        fresh.score(PREFIX, CONTINUATIONS)
    assert other.prefilled >= len(tiny.tokenizer(PREFIX)["input_ids"]) - 1


def kept(tokens: tuple[int, ...], width: int = 4, dtype: torch.dtype = torch.bfloat16, layers: int = 2) -> Prefix:
    """A prefix whose cache holds `layers` layers of keys and values of `width` numbers per token."""
    shape = (1, 1, len(tokens), width)
    cache = DynamicCache()
    for index in range(layers):
        cache.update(torch.zeros(shape, dtype=dtype), torch.zeros(shape, dtype=dtype), index)
    return Prefix(tokens=tokens, cache=cache)


def test_kept_prefixes_are_bounded_in_bytes_and_a_tenant_evicts_only_its_own() -> None:
    entry = kept((1, 2, 3, 4))  # 2 layers x keys and values x 4 tokens x 4 numbers x 2 bytes
    assert PrefixStore.size(entry) == 128
    store = PrefixStore(max_bytes=300)
    store.put("a", entry)
    store.put("b", kept((1, 2, 3, 5)))
    assert store.held_bytes == 256
    assert store.closest("a", (1, 2, 3, 4, 9))[1] == 4  # a's own entry
    store.put("c", kept((7, 7, 7, 7)))  # 384 bytes > 300: a and b keep theirs, c's is not kept
    assert store.scopes() == {"a", "b"}
    assert store.closest("c", (7, 7, 7, 7)) == (None, 0)
    assert store.closest("c", (1, 2, 3, 4)) == (None, 0)  # never another scope's entry
    store.put("b", kept((8, 8, 8, 8)))  # b makes room from its own entries only
    assert store.scopes() == {"a", "b"} and store.closest("b", (1, 2, 3, 5)) == (None, 0)
    assert store.held_bytes == 256


def test_a_tenant_is_held_to_its_own_bound_adapters_included() -> None:
    store = PrefixStore(max_bytes=10_000, tenant_bytes=300)
    store.put("a", kept((1, 1, 1, 1)))
    store.put("a\0policy", kept((2, 2, 2, 2)))  # a trained policy's prompts count against its tenant
    store.put("b", kept((3, 3, 3, 3)))
    store.put("a", kept((4, 4, 4, 4)))  # 3 x 128 > 300 for a: a's least recent goes, b's stays
    assert store.scopes() == {"a", "a\0policy", "b"}
    assert store.closest("a", (1, 1, 1, 1)) == (None, 0)
    assert store.held_bytes == 384


def test_a_float32_prefix_counts_twice_a_bfloat16_one_of_its_length() -> None:
    """The bound is memory: the same tokens cost twice as much where the model runs in float32."""
    store = PrefixStore(max_bytes=300)
    store.put("a", kept((1, 2, 3, 4), dtype=torch.bfloat16))
    store.put("c", kept((1, 2, 3, 4), dtype=torch.float32))  # 256 bytes: no room beside a's 128
    assert store.scopes() == {"a"}
    store.put("a", kept((5, 6, 7, 8), dtype=torch.float32))  # a's own bfloat16 entry makes room
    assert store.scopes() == {"a"}
    assert store.held_bytes == 256 == 2 * PrefixStore.size(kept((1, 2, 3, 4)))


def test_a_prefix_larger_than_the_bound_evicts_nobody_elses() -> None:
    """A prompt longer than the bound is kept alone where nobody else holds an entry (its dialog's next turn
    still reuses it); beside another tenant's entries it is not kept, and theirs stay."""
    store = PrefixStore(max_bytes=100)
    store.put("a", kept((1, 2)))
    store.put("b", kept((5, 6, 7, 8, 9)))
    assert store.scopes() == {"a"}
    alone = PrefixStore(max_bytes=100)
    alone.put("b", kept((5, 6, 7, 8, 9)))
    assert alone.closest("b", (5, 6, 7, 8, 9))[1] == 5
    assert alone.held_bytes == 160


def test_an_unused_prefix_goes_after_the_idle_time() -> None:
    """The memory of a tenant that stopped comes back by time, never by another tenant's request."""
    now = [0.0]
    store = PrefixStore(max_bytes=300, idle_s=60, clock=lambda: now[0])
    store.put("a", kept((1, 2, 3, 4)))
    store.put("b", kept((5, 6, 7, 8)))
    now[0] = 50.0
    assert store.closest("b", (5, 6, 7, 8))[1] == 4  # used: b's entry stays fresh
    now[0] = 70.0
    store.put("c", kept((9, 9, 9, 9)))  # a's, unused for 70 s, went: room for c
    assert store.scopes() == {"b", "c"}


def test_a_kept_prefix_that_a_new_one_extends_goes() -> None:
    """A dialog's next turn extends its last prompt: the store keeps the longer one only, in that scope."""
    store = PrefixStore(max_bytes=10_000)
    first, other, sibling, longer = kept((1, 2, 3)), kept((1, 2, 3)), kept((1, 2, 4)), kept((1, 2, 3, 4, 5))
    store.put("a", first)
    store.put("b", other)
    store.put("a", sibling)
    store.put("a", longer)
    assert store.closest("a", (1, 2, 3))[0] is longer
    assert store.closest("a", (1, 2, 4)) == (sibling, 3)  # not extended: kept
    assert store.closest("b", (1, 2, 3)) == (other, 3)  # another scope's: kept
    assert store.held_bytes == sum(PrefixStore.size(p) for p in (other, sibling, longer))
    shorter = kept((1, 2))
    store.put("a", shorter)  # shorter than a kept one: kept too (an exact hit costs nothing)
    assert store.closest("a", (1, 2)) == (shorter, 2)


def test_the_token_bound_of_older_versions_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A deployment still setting the bound in tokens would otherwise run with the default bound unawares."""
    monkeypatch.setenv("MODEL_PREFIX_CACHE_TOKENS", "4096")
    with pytest.raises(ValidationError, match=r"MODEL_PREFIX_CACHE_TOKENS.*MODEL_PREFIX_CACHE_MB"):
        ModelSettings()
    monkeypatch.delenv("MODEL_PREFIX_CACHE_TOKENS")
    monkeypatch.setenv("MODEL_PREFIX_CACHE_MB", "8")
    assert ModelSettings().prefix_cache_mb == 8


def test_decoding_and_scoring_warn_of_nothing(tiny: CodeModel) -> None:
    """Every `precond infer` printed transformers' FutureWarning about `past_key_values`: the cache is passed
    the way the installed transformers wants it (prefill, decode and the scoring tree)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        with scoped("warnings"):
            tiny.complete(PREFIX, SUFFIXES[:1], 2, Sampling(max_new_tokens=4), "line")
            tiny.score(PREFIX, ["a", "b c"])


def test_rows_read_the_prefix_they_share_instead_of_copying_it(tiny: CodeModel,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The samples' rows hold only what follows the prompt prefix (the prefix's cache is read by all of them), and
    sample and score as rows holding their own copy of it would: given the same tokens, the same logits within
    `layouts.TOLERANCE` (the two layouts' sums may differ in their last bits)."""
    prefix_tokens = len(tiny.tokenizer(PREFIX)["input_ids"])
    sampling = Sampling(max_new_tokens=10, seed=5)
    fresh = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=4)
    widths: list[int] = []
    step = fresh._step

    def measured(batch: Any, *args: Any) -> Any:
        widths.append(batch.cache.layers[0].keys.shape[-2])
        return step(batch, *args)

    monkeypatch.setattr(fresh, "_step", measured)
    with recorded(monkeypatch) as steps:
        shared = fresh.complete(PREFIX, SUFFIXES, 3, sampling, "statement")
    scores = fresh.score(PREFIX, CONTINUATIONS)
    assert widths and max(widths) < 64  # tails, padding and 10 tokens per row, against a prefix of hundreds
    assert prefix_tokens > 200

    monkeypatch.setattr(CodeModel, "_head", lambda self, prefix: None)
    copied = CodeModel(tiny.model, tiny.tokenizer, tiny.info, max_batch=4)
    with replayed(monkeypatch, steps) as differences:
        assert copied.complete(PREFIX, SUFFIXES, 3, sampling, "statement") == shared
    assert max(differences) <= TOLERANCE, f"logits differ by up to {max(differences):.2e}"
    assert copied.score(PREFIX, CONTINUATIONS) == pytest.approx(scores, abs=1e-4)


def test_an_attention_that_reads_no_shared_prefix_gets_a_copy_per_row(tiny_model_dir: Path) -> None:
    """Off CPU the model keeps transformers' attention, which knows nothing of a shared prefix: rows then hold
    their own copy of it and decode as plain greedy decoding does."""
    model = load_code_model(ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", quant="none",
                                          max_batch=4))
    model.model.set_attn_implementation("eager")
    expected = [[reference_greedy(model, PREFIX + suffix, 12, "line")] for suffix in SUFFIXES]
    assert model.complete(PREFIX, SUFFIXES, 1, Sampling(temperature=0, max_new_tokens=12), "line") == expected
    assert model.score(PREFIX, CONTINUATIONS) == pytest.approx(
        [reference_score(model, PREFIX, text) for text in CONTINUATIONS], abs=1e-3)


@pytest.mark.parametrize("top_p", [1.0, 0.9])
def test_a_rows_sampled_token_does_not_depend_on_the_rows_widened_with_it(top_p: float) -> None:
    generator = torch.Generator().manual_seed(0)
    logits = (torch.randn(3 * WIDE_ROWS + 1, 512, generator=generator) * 3).to(torch.bfloat16)
    uniforms = torch.rand(logits.shape[0], generator=generator)
    sampling = Sampling(temperature=0.8, top_p=top_p)
    together = sample_next(logits, sampling, uniforms)
    alone = [int(sample_next(logits[i : i + 1], sampling, uniforms[i : i + 1])) for i in range(logits.shape[0])]
    assert together.tolist() == alone
