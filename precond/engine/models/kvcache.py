"""A key/value cache that grows in place instead of reallocating every decode step.

transformers' `DynamicLayer` appends with `torch.cat`, which copies a row's whole cache at every step of
every layer; on CPU that was over a quarter of a decode step at batch 8 with a 700-token prefix. This layer
keeps spare capacity and writes new keys/values into it, exposing the filled part as a view, so all the
other cache operations (crop, batch select/repeat, deepcopy) keep working on `keys`/`values` unchanged.
"""

from __future__ import annotations

from typing import Any

import torch
from transformers import DynamicCache, DynamicLayer

_HEADROOM = 64
"""Spare positions after each reallocation: enough for a typical completion without another one."""


def _append(
    buffer: torch.Tensor | None, filled: torch.Tensor | None, new: torch.Tensor, capacity: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Write `new` after `filled` into `buffer` (reallocated if `filled` is not its head or it is full): to
    `capacity` positions where that holds them, else with spare room."""
    if filled is None or filled.dim() != new.dim():  # a fresh layer starts from an empty placeholder
        filled = new[..., :0, :]
    length = filled.shape[-2]
    needed = length + new.shape[-2]
    if (
        buffer is None
        or length == 0
        or buffer.data_ptr() != filled.data_ptr()
        or buffer.shape[:-2] != new.shape[:-2]
        or buffer.shape[-2] < needed
    ):
        size = capacity if needed <= capacity else needed + max(needed // 2, _HEADROOM)
        buffer = new.new_empty(*new.shape[:-2], size, new.shape[-1])
        buffer[..., :length, :] = filled
    buffer[..., length:needed, :] = new
    return buffer, buffer[..., :needed, :]


class GrowingLayer(DynamicLayer):  # type: ignore[no-untyped-call]
    """`DynamicLayer` with amortised appends; `keys`/`values` are views of larger buffers. `capacity`: the length
    the layer is known to reach (a prompt prefix's), allocated at once and without spare room."""

    def __init__(self, capacity: int = 0) -> None:
        super().__init__()  # type: ignore[no-untyped-call]
        self.capacity = capacity
        self._key_buffer: torch.Tensor | None = None
        self._value_buffer: torch.Tensor | None = None

    def update(
        self, key_states: torch.Tensor, value_states: torch.Tensor, *args: Any, **kwargs: Any
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.is_initialized:
            self.lazy_initialization(key_states, value_states)
        self._key_buffer, self.keys = _append(self._key_buffer, self.keys, key_states, self.capacity)
        self._value_buffer, self.values = _append(self._value_buffer, self.values, value_states, self.capacity)
        return self.keys, self.values


def growing_cache(config: Any, capacity: int = 0) -> DynamicCache:
    """A `DynamicCache` for `config` whose full-attention layers grow in place (sliding ones stay as is)."""
    cache = DynamicCache(config=config)
    cache.layers = [GrowingLayer(capacity) if type(layer) is DynamicLayer else layer for layer in cache.layers]
    return cache


def compact(cache: DynamicCache) -> DynamicCache:
    """`cache` without its layers' spare room, for keeping: a kept prompt prefix is only read (rows continue it
    in their own caches), and the room a growing layer keeps is up to half its length again."""
    for layer in cache.layers:
        if (isinstance(layer, GrowingLayer) and layer.keys is not None and layer.values is not None
                and layer._key_buffer is not None and layer._key_buffer.shape[-2] > layer.keys.shape[-2]):
            layer.keys, layer.values = layer.keys.clone(), layer.values.clone()
            layer._key_buffer = layer._value_buffer = None
    return cache
