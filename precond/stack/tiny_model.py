"""A randomly initialised two-layer Qwen2 with a small BPE tokenizer, built in-process in about a second.

It exercises the backend's plumbing (cache reuse, batching, stopping, sampling) without the real weights;
what it generates is noise, which is why tests compare it with a reference decode rather than with text.
"""

from __future__ import annotations

from pathlib import Path

import torch
from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
from transformers import PreTrainedTokenizerFast, Qwen2Config, Qwen2ForCausalLM

END = "<|endoftext|>"

_CORPUS = [
    "class USER:\n  def __init__(self):\n    self.informed_slot = defaultdict(lambda: False)\n",
    "  def INFORM(self, slot):\n    assert slot in self.informed_slot, (slot, \\\n      'missing')\n",
    "user = USER()\nsystem = SYSTEM(user)\nuser.INFORM_INTENT('FindRestaurants')\nsystem.REQUEST('city')\n",
    "def f(x: list[int]) -> dict[str, int]:\n    return {'a': x[0]}  # comment\n",
    'if not self.selected and self.no_more:\n    print("done"); raise ValueError("[bad]")\n',
]


def _tokenizer() -> PreTrainedTokenizerFast:
    bpe = Tokenizer(models.BPE())
    bpe.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    bpe.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=400, special_tokens=[END], initial_alphabet=pre_tokenizers.ByteLevel.alphabet()
    )
    bpe.train_from_iterator(_CORPUS * 4, trainer=trainer)
    return PreTrainedTokenizerFast(tokenizer_object=bpe, eos_token=END, pad_token=END)  # type: ignore[no-untyped-call]


def build_tiny_model(directory: Path) -> Path:
    """Write a tiny Qwen2 checkpoint and tokenizer to `directory` (deterministic: seeded init)."""
    tokenizer = _tokenizer()
    config = Qwen2Config(
        vocab_size=len(tokenizer),
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=2,
        max_position_embeddings=4096,
        initializer_range=0.2,
        eos_token_id=tokenizer.eos_token_id,
        pad_token_id=tokenizer.pad_token_id,
        bos_token_id=None,
        tie_word_embeddings=True,
    )
    torch.manual_seed(0)
    model = Qwen2ForCausalLM(config)
    model.save_pretrained(directory)
    tokenizer.save_pretrained(directory)
    return directory
