"""Attention for CPU decoding: grouped-query attention as two batched matmuls.

torch's CPU SDPA kernel is tuned for long queries; with one query token per row (decoding) it spends ~10 ms
per layer at batch 8 on a 700-token context, against ~0.4 ms for plain matmuls, and transformers' other
paths first copy the key/value heads once per query group. Grouping the query heads that share a key/value
head instead reads the cache once and keeps every step's attention a few percent of the forward pass.
"""

from __future__ import annotations

from typing import Any

import torch

NAME = "precond_grouped"


def grouped_attention(
    module: torch.nn.Module,
    query: torch.Tensor,
    key: torch.Tensor,
    value: torch.Tensor,
    attention_mask: torch.Tensor | None,
    scaling: float | None = None,
    dropout: float = 0.0,
    head: Any = None,
    **kwargs: Any,
) -> tuple[torch.Tensor, None]:
    """query [B, H, Q, D], key/value [B, KV, L, D], additive mask [B, 1, Q, L] -> output [B, Q, H, D].

    `head`: a one-row cache (a prompt prefix) that every row continues. Its keys and values of this layer come
    before `key`/`value` in every row, unmasked, and are read once for the whole batch: the rows of a prompt's
    samples hold only what follows the prefix, never a copy of it each (`backend`)."""
    batch, heads, q_len, dim = query.shape
    kv_heads, kv_len = key.shape[1], key.shape[2]
    groups = heads // kv_heads
    scale = dim**-0.5 if scaling is None else scaling
    grouped = query.reshape(batch, kv_heads, groups * q_len, dim)
    scores = (torch.matmul(grouped, key.transpose(-1, -2)) * scale).view(batch, kv_heads, groups, q_len, kv_len)
    if attention_mask is not None:
        scores = scores + attention_mask[:, :, None]
    if head is None:
        probs = torch.softmax(scores.float(), dim=-1).to(value.dtype)
        out = torch.matmul(probs.view(batch, kv_heads, groups * q_len, kv_len), value)
        return out.view(batch, heads, q_len, dim).transpose(1, 2).contiguous(), None
    layer = head.layers[module.layer_idx]
    head_keys, head_values = layer.keys[0], layer.values[0]
    shared = head_keys.shape[1]
    rows = grouped.transpose(0, 1).reshape(kv_heads, batch * groups * q_len, dim)
    head_scores = (torch.matmul(rows, head_keys.transpose(-1, -2)) * scale).view(kv_heads, batch, groups, q_len, shared)
    probs = torch.softmax(torch.cat([head_scores.transpose(0, 1), scores], dim=-1).float(), dim=-1).to(value.dtype)
    # Both halves summed in float32 and rounded once, as one product over all columns would be.
    wide = probs.float()
    head_probs, own_probs = wide[..., :shared], wide[..., shared:]
    head_out = torch.matmul(head_probs.transpose(0, 1).reshape(kv_heads, batch * groups * q_len, shared),
                            head_values.float())
    own_out = torch.matmul(own_probs.reshape(batch, kv_heads, groups * q_len, kv_len), value.float())
    out = (own_out + head_out.view(kv_heads, batch, groups * q_len, dim).transpose(0, 1)).to(value.dtype)
    return out.view(batch, heads, q_len, dim).transpose(1, 2).contiguous(), None


def use_grouped_attention(model: Any) -> None:
    """Switch `model` to `grouped_attention`, with transformers' additive (eager) masks.

    Additive masks also keep a padded query that may attend to nothing finite (a pad in a batch with no
    shared prefix) at a uniform softmax instead of NaN.
    """
    from transformers import AttentionInterface
    from transformers.masking_utils import AttentionMaskInterface, eager_mask

    AttentionInterface.register(NAME, grouped_attention)
    AttentionMaskInterface.register(NAME, eager_mask)
    model.set_attn_implementation(NAME)
