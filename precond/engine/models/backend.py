"""Raw code completion with a shared prompt prefix: the engine's bottleneck, so built for throughput.

Every precondition prompt of a domain shares a long prefix (observation functions and a demonstration,
~700 tokens) and differs only in a short suffix (the action's `def` ending in `assert`). So:

* the prefix goes through the model once; its key/value cache is held once and read by every row (the rows
  hold only what follows it: `attention.grouped_attention`'s `head`), never recomputed, and kept between calls
  so that later calls with the same prefix (per-action calls, a dialog's next turn) reuse it too: kept per
  tenant (`engine.models.prefixes`), so no tenant's work speeds up or reveals another's;
* the n samples of a suffix, and the rows of several suffixes, are decoded as one batch, refilled from the
  queue as rows finish (continuous batching) so the batch never drains to a few slow stragglers;
* the suffixes' tails are left-padded after the shared prefix, so every row ends at the same column and one
  forward pass serves all of them (pads are masked out, positions are per row);
* rows stop independently (end of line or statement, EOS, token budget) and finished rows leave the batch.

Prefix and suffix are tokenised jointly and split at the longest common token prefix: tokenising them apart
would put a token boundary before "assert" that the model never saw in training, and degrade completions.
"""

from __future__ import annotations

import copy
import hashlib
import logging
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from precond.engine.models.attention import NAME as ATTENTION
from precond.engine.models.attention import use_grouped_attention
from precond.engine.models.kvcache import GrowingLayer, compact, growing_cache
from precond.engine.models.prefixes import Prefix, PrefixStore
from precond.engine.models.stopping import StopRule, stop_index
from precond.engine.models.tree import TokenTree, groups
from precond.engine.models.weights import load_weights, quantized, resident, serving_weights
from precond.engine.scope import current as current_scope
from precond.engine.settings import PREFIX_CACHE_MB, ModelSettings
from precond_client.schemas import ModelInfo
from precond_client.schemas.errors import Cancelled

logger = logging.getLogger(__name__)

__all__ = ["CodeModel", "GenerationCancelled", "Sampling", "StopRule", "load_code_model"]

MIB = 1 << 20

PREFILL_CHUNK = 128
"""The prefix is run in chunks at these fixed boundaries, so the cache a call reuses is bit-identical to the
one it would compute itself: outputs never depend on what an earlier call left behind."""
MAX_TREE_NODES = 1024
"""Tokens of scored continuations per forward pass (its logits are up to this many vocabulary rows)."""

_TOP_K_FIRST = 256
"""Top-p looks at the best 256 tokens first; only rows whose nucleus is wider pay for a full-vocab sort."""
WIDE_ROWS = 4
"""Logit rows widened to float32 at a time for a softmax: a row over the embedded model's 151,936 tokens is 600 KB
in float32, so widening all 32 rows of a batch (or a scoring tree's rows) at once costs 19 MB per copy. Each row's
softmax is computed on its own, so the blocks change no number."""


class GenerationCancelled(Cancelled):
    """`should_stop` turned true between two decode steps."""

    def __init__(self) -> None:
        super().__init__("generation cancelled")


@dataclass(frozen=True)
class Sampling:
    temperature: float = 0.8  # 0 => greedy (then n is forced to 1)
    top_p: float = 0.95
    max_new_tokens: int = 48
    seed: int = 0

    def __post_init__(self) -> None:
        if self.temperature < 0 or not 0 < self.top_p <= 1 or self.max_new_tokens < 1:
            raise ValueError(f"invalid sampling parameters {self}")

    @property
    def greedy(self) -> bool:
        return self.temperature <= 0


@dataclass
class _Row:
    """One sequence being decoded: which suffix it continues and what it produced so far."""

    suffix: int
    key: str = ""
    """What the row's random draws are keyed by (its suffix's text), with `sample`, the seed and the step."""
    sample: int = 0
    tokens: list[int] = field(default_factory=list)
    text: str | None = None


@dataclass
class _Batch:
    """Rows decoded together; `mask` covers every column of `cache`, `positions` are each row's next position.

    `head`: the prompt prefix's cache that every row continues, shared (`CodeModel._head`); `cache` then holds only what
    follows it in each row. None where each row's `cache` holds the prefix too."""

    rows: list[_Row]
    cache: Any
    logits: torch.Tensor
    mask: torch.Tensor
    positions: torch.Tensor
    head: Any = None


@dataclass
class _Tails:
    """The prefix followed by each distinct tail, one row per tail, ready to sample: what a row starts from.

    Kept between refills of one call, so rows of a suffix that land in a later refill (n larger than the free
    slots) copy their tail's row instead of prefilling the tail again: each prompt is prefilled once per call.
    """

    keys: list[tuple[int, ...]]
    batch: _Batch


def _select(batch: _Batch, rows: Sequence[_Row], index: torch.Tensor, keep: bool = True) -> _Batch:
    """A new batch of `batch`'s rows at `index` (repeats allowed); `batch` is left as it was if `keep`."""
    cache = copy.deepcopy(batch.cache) if keep else batch.cache
    cache.batch_select_indices(index)
    return _Batch(list(rows), cache, batch.logits[index], batch.mask[index], batch.positions[index], batch.head)


def _mergeable(cache: Any) -> bool:
    """Rows can only join a running batch where every layer is a plain full-attention cache."""
    return all(isinstance(layer, GrowingLayer) for layer in cache.layers)


def _widen(tensor: torch.Tensor, width: int, dim: int) -> torch.Tensor:
    """Insert zero (masked) columns before the rows' own so that `tensor` spans `width` columns."""
    missing = width - tensor.shape[dim]
    if missing == 0:
        return tensor
    shape = list(tensor.shape)
    shape[dim] = missing
    return torch.cat([tensor.new_zeros(shape), tensor], dim=dim)


def _merge(running: _Batch, joining: _Batch) -> _Batch:
    """One batch of both (rows continuing one shared `head`): the shorter rows get padding columns first.

    Attention order is by column and positions are per row, so masked columns after the prefix change nothing.
    """
    width = max(running.mask.shape[1], joining.mask.shape[1])
    for ours, theirs in zip(running.cache.layers, joining.cache.layers, strict=True):
        for name in ("keys", "values"):
            merged = [_widen(getattr(layer, name), width, dim=-2) for layer in (ours, theirs)]
            setattr(ours, name, torch.cat(merged, dim=0))
    return _Batch(
        rows=running.rows + joining.rows,
        cache=running.cache,
        logits=torch.cat([running.logits, joining.logits]),
        mask=torch.cat([_widen(b.mask, width, dim=1) for b in (running, joining)]),
        positions=torch.cat([running.positions, joining.positions]),
        head=running.head,
    )


def _common_prefix_length(a: Sequence[int], b: Sequence[int]) -> int:
    n = min(len(a), len(b))
    for i in range(n):
        if a[i] != b[i]:
            return i
    return n


def uniform(seed: int, row: _Row) -> float:
    """The row's random number for its next token: a function of the seed, the row's suffix and sample index and
    the step only, never of the batch it is decoded in. So a prompt's samples are the same whatever else is
    sampled beside it (other actions, other prompts) and whatever `max_batch` the server runs."""
    digest = hashlib.blake2b(f"{seed}/{row.sample}/{len(row.tokens)}/{row.key}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big") / 2.0**64


def sample_next(logits: torch.Tensor, sampling: Sampling, uniforms: torch.Tensor) -> torch.Tensor:
    """Temperature and nucleus (top-p) sampling of one token per row by inverting its distribution at the row's
    own uniform number (`uniform`); argmax when greedy."""
    if sampling.greedy:
        return logits.argmax(dim=-1)
    probs = torch.empty(logits.shape, dtype=torch.float32, device=logits.device)
    for start in range(0, logits.shape[0], WIDE_ROWS):
        block = logits[start : start + WIDE_ROWS].float().div_(sampling.temperature)
        probs[start : start + WIDE_ROWS] = torch.softmax(block, dim=-1)
    if sampling.top_p >= 1:
        top_probs, top_ids = probs, None
    else:
        k = min(_TOP_K_FIRST, probs.shape[-1])
        top_probs, top_ids = probs.topk(k, dim=-1)
        if not bool((top_probs.sum(dim=-1) >= sampling.top_p).all()):
            top_probs, top_ids = probs.sort(dim=-1, descending=True)
        outside = top_probs.cumsum(dim=-1) - top_probs > sampling.top_p
        top_probs = top_probs.masked_fill(outside, 0.0)
    cumulative = top_probs.cumsum(dim=-1)
    target = uniforms.to(cumulative)[:, None] * cumulative[:, -1:]
    choice = torch.searchsorted(cumulative, target, right=True).clamp(max=cumulative.shape[-1] - 1)
    return choice.squeeze(-1) if top_ids is None else top_ids.gather(-1, choice).squeeze(-1)


class CodeModel:
    """A causal code model behind `complete`; one call at a time (the cache it keeps is not shareable)."""

    def __init__(self, model: Any, tokenizer: Any, info: ModelInfo, max_batch: int = 32,
                 prefix_bytes: int = PREFIX_CACHE_MB * MIB, known_calls: tuple[str, ...] = (),
                 prefixes: PrefixStore | None = None) -> None:
        self.model = model
        self.known_calls = known_calls
        """A fine-tuned policy's vocabulary (`TrainPolicyResult.calls`); empty for the base model."""
        self.tokenizer = tokenizer
        self.info = info
        self.max_batch = max_batch
        self.prefix_bytes = prefix_bytes
        self.device = next(model.parameters()).device
        self._stop_ids = self._end_token_ids()
        self._prefixes = PrefixStore(prefix_bytes) if prefixes is None else prefixes
        """Shared with the adapted copies of this model (`with_adapter`), whose entries are their own
        (`_scope`): one bound on the memory of all kept prefixes."""
        self._lock = threading.Lock()

    def _end_token_ids(self) -> frozenset[int]:
        """EOS from both tokenizer and generation config, and every special token: raw code has none."""
        ids = set(self.tokenizer.all_special_ids)
        config_eos = getattr(self.model.generation_config, "eos_token_id", None)
        if isinstance(config_eos, int):
            ids.add(config_eos)
        elif config_eos:
            ids.update(config_eos)
        if self.tokenizer.eos_token_id is not None:
            ids.add(self.tokenizer.eos_token_id)
        return frozenset(ids)

    def complete(
        self,
        prefix: str,
        suffixes: Sequence[str],
        n: int,
        sampling: Sampling,
        stop: StopRule,
        should_stop: Callable[[], bool] | None = None,
    ) -> list[list[str]]:
        """For each suffix, n completions of prefix+suffix (the text after the suffix, cut before the stop).

        Raises GenerationCancelled when `should_stop()` turns true (checked between decode steps).
        """
        if n < 1:
            raise ValueError("n must be at least 1")
        if not suffixes:
            return []
        n = 1 if sampling.greedy else n
        with self._lock, torch.inference_mode():
            prompts = [self._encode(prefix + suffix) for suffix in suffixes]
            shared = min(
                min(len(p) for p in prompts) - 1,
                min(_common_prefix_length(prompts[0], p) for p in prompts),
            )
            prefix_cache = self._prefix_cache(tuple(prompts[0][:shared]), should_stop)
            rows = [_Row(suffix=i, key=suffixes[i], sample=j) for i in range(len(prompts)) for j in range(n)]
            tails = [prompts[i][shared:] for i in range(len(prompts))]
            self._run(rows, tails, prefix_cache, sampling, stop, should_stop)
        results: list[list[str]] = [[] for _ in suffixes]
        for row in rows:
            results[row.suffix].append(row.text or "")
        return results

    def score(
        self, prefix: str, continuations: Sequence[str], should_stop: Callable[[], bool] | None = None
    ) -> list[float]:
        """Log-likelihood of each continuation after `prefix`: the sum over the continuation's own tokens.

        This is how the engine lets the model *choose* among candidates that were already executed and
        validated (enumerated conditions, allowed next calls) instead of hoping free samples hit them. The
        prefix is prefilled once (and kept, like `complete`'s); the continuations run together as one token
        tree over it (precond/engine/models/tree.py: each shared token once, one copy of the cache), `MAX_TREE_NODES`
        tokens per forward pass. Tokens are split where the jointly tokenised texts diverge from the prefix
        alone, so a boundary token merged across prefix and continuation counts for the continuation.
        """
        if not continuations:
            return []
        with self._lock, torch.inference_mode():
            head = self._encode(prefix)
            fulls = [self._encode(prefix + text) for text in continuations]
            starts = [max(1, _common_prefix_length(head, full)) for full in fulls]
            shared = max(0, min(starts) - 1)  # the token before each first scored one stays in the tail
            prefix_cache = self._prefix_cache(tuple(fulls[0][:shared]), should_stop)
            tails = [full[shared:] for full in fulls]
            scores = [0.0] * len(fulls)
            for group in groups(tails, MAX_TREE_NODES):
                if should_stop is not None and should_stop():
                    raise GenerationCancelled()
                tree = TokenTree.of([tails[i] for i in group])
                logprobs = self._tree_logprobs(tree, prefix_cache)
                for i, path in zip(group, tree.paths, strict=True):
                    scores[i] = sum(logprobs[node] for node in path if tree.depths[node] >= starts[i] - shared)
        return scores

    def _tree_logprobs(self, tree: TokenTree, prefix: Prefix) -> list[float]:
        """log p(node's token | prefix and the node's ancestors) for every node (0.0 for a root, unscored)."""
        size = len(tree)
        inner = tree.inner()
        if not inner:
            return [0.0] * size
        shared = len(prefix.tokens)
        head = self._head(prefix)
        columns = 0 if head is not None else shared  # the prefix's columns in the tree's own cache
        allowed = torch.cat([torch.ones(size, columns, dtype=torch.bool), tree.ancestor_mask()], dim=1)
        dtype = next(self.model.parameters()).dtype
        mask = torch.zeros(1, 1, size, columns + size, dtype=dtype, device=self.device)
        mask.masked_fill_(~allowed.to(self.device)[None, None], torch.finfo(dtype).min)
        logits = self.model(
            input_ids=torch.tensor([tree.tokens], device=self.device),
            attention_mask=mask,
            position_ids=torch.tensor([[shared + d for d in tree.depths]], device=self.device),
            cache=growing_cache(self.model.config) if head is not None else copy.deepcopy(prefix.cache),
            use_cache=True,
            logits_to_keep=torch.tensor(inner, device=self.device),
            head=head,
        ).logits[0]
        children: dict[int, list[tuple[int, int]]] = {}  # a logit row -> the (node, token) pairs it scores
        row = {node: k for k, node in enumerate(inner)}
        for node, (parent, token) in enumerate(zip(tree.parents, tree.tokens, strict=True)):
            if parent >= 0:
                children.setdefault(row[parent], []).append((node, token))
        logprobs = [0.0] * size
        for start in range(0, len(inner), WIDE_ROWS):  # widened a few rows at a time (`WIDE_ROWS`)
            block = torch.log_softmax(logits[start : start + WIDE_ROWS].float(), dim=-1)
            for k in range(start, min(start + WIDE_ROWS, len(inner))):
                for node, token in children.get(k, []):
                    logprobs[node] = float(block[k - start, token])
        return logprobs

    def _head(self, prefix: Prefix) -> Any:
        """`prefix`'s cache for rows to share (`_Batch.head`), or None where each row must hold a copy: an empty
        prefix, layers other than full attention (a sliding window masks the prefix's columns per row), or an
        attention other than `grouped_attention` (off CPU), which would not read a `head`."""
        shareable = self.model.config._attn_implementation == ATTENTION and _mergeable(prefix.cache)
        return prefix.cache if prefix.tokens and shareable else None

    def _encode(self, text: str) -> list[int]:
        return list(self.tokenizer(text)["input_ids"])

    def _forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor, position_ids: torch.Tensor,
                 cache: Any, head: Any) -> torch.Tensor:
        """Last-position logits only: the vocabulary projection is a quarter of a 0.5B model's weights."""
        out = self.model(
            input_ids=input_ids,
            attention_mask=attention_mask,
            position_ids=position_ids,
            cache=cache,
            use_cache=True,
            logits_to_keep=1,
            head=head,
        )
        logits: torch.Tensor = out.logits[:, -1, :]
        return logits

    def _prefix_cache(self, tokens: tuple[int, ...], should_stop: Callable[[], bool] | None = None) -> Prefix:
        """The cache of `tokens`, reusing the closest one kept in this scope (`engine.scope`, the job's tenant)
        up to the last chunk boundary both share."""
        scope = current_scope() if self.info.adapter is None else f"{current_scope()}\0{self.info.adapter}"
        kept, shared = self._prefixes.closest(scope, tokens)
        if kept is not None and kept.tokens == tokens:
            return kept
        reuse = shared // PREFILL_CHUNK * PREFILL_CHUNK
        if reuse > 0 and kept is not None and _mergeable(kept.cache):  # the kept columns, into a cache of its size
            cache = growing_cache(self.model.config, capacity=len(tokens))
            for index, layer in enumerate(kept.cache.layers):
                cache.update(layer.keys[..., :reuse, :], layer.values[..., :reuse, :], index)
        elif reuse > 0 and kept is not None:
            cache = copy.deepcopy(kept.cache)
            if reuse < len(kept.tokens):
                cache.crop(reuse - len(kept.tokens))
        else:
            reuse, cache = 0, growing_cache(self.model.config, capacity=len(tokens))
        for start in range(reuse, len(tokens), PREFILL_CHUNK):
            if should_stop is not None and should_stop():
                raise GenerationCancelled()  # a long prompt's prefill takes seconds on a CPU
            chunk = torch.tensor([tokens[start : start + PREFILL_CHUNK]], device=self.device)
            end = start + chunk.shape[1]
            self.model(
                input_ids=chunk,
                attention_mask=torch.ones(1, end, dtype=torch.long, device=self.device),
                position_ids=torch.arange(start, end, device=self.device)[None],
                cache=cache,
                use_cache=True,
                logits_to_keep=1,
            )
        entry = Prefix(tokens=tokens, cache=compact(cache))
        self._prefixes.put(scope, entry)
        return entry

    def _run(
        self,
        rows: Sequence[_Row],
        tails: Sequence[Sequence[int]],
        prefix: Prefix,
        sampling: Sampling,
        stop: StopRule,
        should_stop: Callable[[], bool] | None,
    ) -> None:
        """Decode all rows with continuous batching: free slots are refilled from the queue as rows finish.

        A batch drained to its few longest rows decodes at batch-1 speed (memory-bound, ~5 tokens/s on one
        CPU core) while a full one shares each weight read across all rows; refilling keeps it full.
        """
        pending = deque(rows)
        batch: _Batch | None = None
        kept: _Tails | None = None
        while pending or batch is not None:
            free = self.max_batch - (len(batch.rows) if batch else 0)
            if pending and (batch is None or (free >= self._refill_at and _mergeable(batch.cache))):
                taken = [pending.popleft() for _ in range(min(free, len(pending)))]
                fresh, kept = self._start(taken, [tails[row.suffix] for row in taken], prefix, kept, bool(pending))
                batch = fresh if batch is None else _merge(batch, fresh)
            if should_stop is not None and should_stop():
                raise GenerationCancelled()
            assert batch is not None
            batch = self._step(batch, sampling, stop)

    @property
    def _refill_at(self) -> int:
        """Free slots worth a refill: each one costs a tail prefill and a copy of the rows' own caches."""
        return max(1, self.max_batch // 4)

    def _start(
        self,
        rows: Sequence[_Row],
        tails: Sequence[Sequence[int]],
        prefix: Prefix,
        kept: _Tails | None,
        keep: bool,
    ) -> tuple[_Batch, _Tails | None]:
        """The batch of `rows`, ready to sample their first tokens, and the distinct tails' rows to keep.

        Each distinct tail is run once, padded after the prefix, or copied from `kept` when an earlier start
        of this call already ran it; rows sharing a tail (the n samples of a prompt) get copies of its cache
        row and logits. So n samples of a prompt cost one prefill, however the batch is refilled. `keep`:
        rows are still pending, so the distinct tails' rows are returned for the next start.
        """
        keys = [tuple(tail) for tail in tails]
        distinct = sorted(set(keys))
        reusable = kept is not None and _mergeable(kept.batch.cache)
        reused = [key for key in distinct if reusable and kept is not None and key in kept.keys]
        missing = [key for key in distinct if key not in reused]
        parts = []
        if reused:
            assert kept is not None
            index = torch.tensor([kept.keys.index(key) for key in reused], device=self.device)
            parts.append(_select(kept.batch, [], index))
        if missing:
            parts.append(self._prefill_tails(missing, prefix))
        start = parts[0] if len(parts) == 1 else _merge(parts[0], parts[1])
        order = reused + missing
        source = torch.tensor([order.index(key) for key in keys], device=self.device)
        return _select(start, rows, source, keep), _Tails(order, start) if keep else None

    def _prefill_tails(self, tails: Sequence[Sequence[int]], prefix: Prefix) -> _Batch:
        """One row per tail, the tails run in one forward pass, left-padded, over the prefix's cache: shared by
        the rows (`_head`), or copied into each where it cannot be."""
        shared = len(prefix.tokens)
        ids, mask = self._left_pad(tails)
        positions = (shared + mask.cumsum(1) - 1).clamp(min=shared)
        head = self._head(prefix)
        if head is not None:
            cache = growing_cache(self.model.config)
        else:
            cache = copy.deepcopy(prefix.cache)
            if shared:
                cache.batch_repeat_interleave(len(tails))
            mask = torch.cat([mask.new_ones(len(tails), shared), mask], dim=1)
        logits = self._forward(ids, mask, positions, cache, head)
        return _Batch([], cache, logits, mask, positions[:, -1] + 1, head)

    def _left_pad(self, tails: Sequence[Sequence[int]]) -> tuple[torch.Tensor, torch.Tensor]:
        pad = self.tokenizer.pad_token_id if self.tokenizer.pad_token_id is not None else 0
        width = max(len(tail) for tail in tails)
        ids = [[pad] * (width - len(tail)) + list(tail) for tail in tails]
        mask = [[0] * (width - len(tail)) + [1] * len(tail) for tail in tails]
        return torch.tensor(ids, device=self.device), torch.tensor(mask, device=self.device)

    def _step(self, batch: _Batch, sampling: Sampling, stop: StopRule) -> _Batch | None:
        """Sample one token per row, retire finished rows, and run the rest one position further."""
        uniforms = torch.tensor([0.0 if sampling.greedy else uniform(sampling.seed, row) for row in batch.rows])
        next_ids = sample_next(batch.logits, sampling, uniforms)
        tokens = next_ids.tolist()
        keep = [i for i, row in enumerate(batch.rows) if not self._advance(row, tokens[i], stop, sampling)]
        if not keep:
            return None
        if len(keep) < len(batch.rows):
            index = torch.tensor(keep, device=self.device)
            batch.cache.batch_select_indices(index)
            batch.rows = [batch.rows[i] for i in keep]
            batch.mask, batch.positions, next_ids = batch.mask[index], batch.positions[index], next_ids[index]
        batch.mask = torch.cat([batch.mask, batch.mask.new_ones(len(keep), 1)], dim=1)
        batch.logits = self._forward(next_ids[:, None], batch.mask, batch.positions[:, None], batch.cache,
                                     batch.head)
        batch.positions = batch.positions + 1
        return batch

    def _advance(self, row: _Row, token: int, stop: StopRule, sampling: Sampling) -> bool:
        """Append `token` to `row`; True (and `row.text` set) once the row is finished."""
        ended = token in self._stop_ids
        if not ended:
            row.tokens.append(token)
        text = self.tokenizer.decode(row.tokens)
        cut = stop_index(text, stop)
        if cut is not None:
            row.text = text[:cut]
        elif ended or len(row.tokens) >= sampling.max_new_tokens:
            row.text = text
        return row.text is not None


def load_code_model(settings: ModelSettings, adapter: Path | None = None) -> CodeModel:
    """The serving model; with `adapter` (a trained policy, `engine.models.adapters`) merged into full-width
    weights, then quantized (the evaluation's fine-tuned policies; a service keeps adapters unmerged,
    `with_adapter`)."""
    calls: tuple[str, ...] = ()
    if adapter is None:
        weights = serving_weights(settings)
    else:
        from precond.engine.models.adapters import merge_adapter

        weights = load_weights(settings)
        name, trained = merge_adapter(weights.model, adapter, weights.info)
        weights = replace(weights, info=weights.info.model_copy(update={"adapter": name}))
        calls = tuple(trained.calls)
        weights = quantized(weights, settings.quant)
    model, info = weights.model, weights.info
    model.eval()
    resident(model)
    if weights.device.type == "cpu":
        use_grouped_attention(model)
    logger.info("loaded %s on %s (%s; %s)%s", info.name, info.device, info.dtype_reason, info.quant_reason,
                f", policy adapter {info.adapter}" if info.adapter else "")
    tenant_mb = settings.prefix_cache_mb if settings.prefix_cache_tenant_mb is None else settings.prefix_cache_tenant_mb
    prefixes = PrefixStore(settings.prefix_cache_mb * MIB, tenant_mb * MIB, settings.prefix_cache_idle_s)
    return CodeModel(model, weights.tokenizer, info, max_batch=settings.max_batch,
                     prefix_bytes=settings.prefix_cache_mb * MIB, known_calls=calls, prefixes=prefixes)


class LoraLinear(torch.nn.Module):
    """A shared layer plus an adapter's low-rank change, unmerged: `base(x) + (x @ a.T) @ b.T`."""

    def __init__(self, base: torch.nn.Module, a: torch.Tensor, b: torch.Tensor) -> None:
        super().__init__()
        self.base = base
        self.a: torch.Tensor
        self.b: torch.Tensor
        self.register_buffer("a", a)
        self.register_buffer("b", b)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.base(x)
        return out + (x @ self.a.T) @ self.b.T


def with_adapter(base: CodeModel, directory: Path) -> CodeModel:
    """`base` with a trained policy's low-rank changes beside the projections it trains (`LoraLinear`), unmerged:
    every weight of `base` is shared, full-width or int8, and stays exactly as it was. So a warm adapter costs its
    own tensors (rank x (in + out) per projection: ~2 MB for the embedded model at rank 8 in bfloat16) and a copy
    of the module tree, and building it is a read of the adapter (no merge). Its prompt prefixes live in `base`'s
    store, keyed by tenant and adapter, within the one byte bound."""
    from precond.engine.models.adapters import lora_weights

    dtype = next(base.model.parameters()).dtype
    name, trained, pairs = lora_weights(base.model, directory, base.info)
    leaves: dict[int, Any] = {id(m): m for m in base.model.modules() if next(m.children(), None) is None}
    leaves.update({id(t): t for t in [*base.model.parameters(), *base.model.buffers()]})
    leaves[id(base.model.config)] = base.model.config
    model = copy.deepcopy(base.model, memo=leaves)
    for module, lora in pairs.items():
        parent, _, child = module.rpartition(".")
        owner = model.get_submodule(parent)
        setattr(owner, child, LoraLinear(getattr(owner, child), lora.a.to(dtype), lora.b.to(dtype)))
    model.eval()
    return CodeModel(model, base.tokenizer, base.info.model_copy(update={"adapter": name}),
                     max_batch=base.max_batch, prefix_bytes=base.prefix_bytes, known_calls=tuple(trained.calls),
                     prefixes=base._prefixes)
