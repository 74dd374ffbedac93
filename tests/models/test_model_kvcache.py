from __future__ import annotations

import copy

import torch
from transformers import DynamicCache, DynamicLayer

from precond.engine.models.kvcache import GrowingLayer, compact


def _states(batch: int, length: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn(batch, 2, length, 8, generator=generator), torch.randn(
        batch, 2, length, 8, generator=generator
    )


def test_growing_layer_behaves_like_dynamic_layer() -> None:
    growing, plain = GrowingLayer(), DynamicLayer()
    for layer in (growing, plain):
        layer.update(*_states(1, 100, 0))
        layer.crop(-30)
        layer.batch_repeat_interleave(3)
        for step in range(70):  # crosses the spare capacity, so it reallocates at least once
            layer.update(*_states(3, 1, step + 1))
        layer.batch_select_indices(torch.tensor([2, 0]))
        layer.update(*_states(2, 5, 99))
    assert torch.equal(growing.keys, plain.keys)
    assert torch.equal(growing.values, plain.values)


def test_copies_do_not_share_storage() -> None:
    layer = GrowingLayer()
    layer.update(*_states(1, 10, 0))
    clone = copy.deepcopy(layer)
    clone.update(*_states(1, 1, 1))
    layer.update(*_states(1, 1, 2))
    assert not torch.equal(clone.keys, layer.keys)
    assert torch.equal(clone.keys[..., :10, :], layer.keys[..., :10, :])


def test_a_layer_of_known_length_is_allocated_once_and_kept_without_spare_room() -> None:
    layer = GrowingLayer(capacity=30)
    layer.update(*_states(1, 10, 0))
    buffer = layer.keys.untyped_storage().data_ptr()
    layer.update(*_states(1, 20, 1))
    assert layer.keys.untyped_storage().data_ptr() == buffer
    assert layer.keys.untyped_storage().nbytes() == layer.keys.nbytes  # exactly 30 positions

    grown = DynamicCache()
    grown.layers = [GrowingLayer()]
    grown.update(*_states(1, 10, 0), 0)
    keys = grown.layers[0].keys.clone()
    assert grown.layers[0].keys.untyped_storage().nbytes() > keys.nbytes  # spare room
    compact(grown)
    assert torch.equal(grown.layers[0].keys, keys)
    assert grown.layers[0].keys.untyped_storage().nbytes() == keys.nbytes
