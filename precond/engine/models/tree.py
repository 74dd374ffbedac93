"""Continuations to score as one token tree: what several of them share is computed once.

Scoring the allowed next calls (`system.INFORM('phone_number')`, `system.INFORM('address')`, ...) as a batch
of rows copies the prompt's key/value cache once per row and recomputes every shared head (`system.INFORM('`)
per row; with a 1,500-token dialog and 40 calls the copies alone are most of a request. As a tree, the
continuations are one sequence of distinct prefixes (a trie, parents before children), in one forward pass
over the prompt's cache, each node attending to the prompt and its own ancestors only (`ancestor_mask`): the
same log-likelihoods, one cache, and every shared token once.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class TokenTree:
    tokens: list[int]
    parents: list[int]
    """Index of each node's parent; -1 for a root (the token before the first scored one has no parent)."""
    depths: list[int]
    paths: list[list[int]]
    """Per continuation, its nodes from the root."""

    @classmethod
    def of(cls, tails: Sequence[Sequence[int]]) -> TokenTree:
        tokens: list[int] = []
        parents: list[int] = []
        depths: list[int] = []
        children: dict[tuple[int, int], int] = {}
        paths: list[list[int]] = []
        for tail in tails:
            node, path = -1, []
            for depth, token in enumerate(tail):
                key = (node, token)
                if key not in children:
                    children[key] = len(tokens)
                    tokens.append(token)
                    parents.append(node)
                    depths.append(depth)
                node = children[key]
                path.append(node)
            paths.append(path)
        return cls(tokens, parents, depths, paths)

    def __len__(self) -> int:
        return len(self.tokens)

    def inner(self) -> list[int]:
        """Nodes with a child: only their next-token distributions are needed."""
        return sorted({p for p in self.parents if p >= 0})

    def ancestor_mask(self) -> torch.Tensor:
        """[nodes, nodes] boolean: row i is true at i and each of its ancestors."""
        size = len(self.tokens)
        mask = torch.zeros(size, size, dtype=torch.bool)
        for i, parent in enumerate(self.parents):
            if parent >= 0:
                mask[i] = mask[parent]
            mask[i, i] = True
        return mask


def groups(tails: Sequence[Sequence[int]], max_nodes: int) -> list[list[int]]:
    """Consecutive continuations whose tokens together stay within `max_nodes` (each group at least one):
    bounds the size of one forward pass (its logits are nodes x vocabulary)."""
    out: list[list[int]] = []
    size = 0
    for i, tail in enumerate(tails):
        if not out or size + len(tail) > max_nodes:
            out.append([])
            size = 0
        out[-1].append(i)
        size += len(tail)
    return out
