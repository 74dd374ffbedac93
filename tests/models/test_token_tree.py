"""The token tree that scores continuations together: shared heads once, each path its own tokens."""

import torch

from precond.engine.models.tree import TokenTree, groups


def test_shared_heads_are_one_node_and_paths_spell_each_tail() -> None:
    tails = [[1, 2, 3], [1, 2, 4], [1, 5], [1, 2, 3]]
    tree = TokenTree.of(tails)
    assert tree.tokens == [1, 2, 3, 4, 5]
    assert tree.parents == [-1, 0, 1, 1, 0]
    assert tree.depths == [0, 1, 2, 2, 1]
    assert [[tree.tokens[n] for n in path] for path in tree.paths] == tails
    assert tree.paths[0] == tree.paths[3]
    assert tree.inner() == [0, 1]


def test_a_node_sees_itself_and_its_ancestors_only() -> None:
    tree = TokenTree.of([[1, 2, 3], [1, 4]])
    expected = torch.tensor([
        [1, 0, 0, 0],
        [1, 1, 0, 0],
        [1, 1, 1, 0],
        [1, 0, 0, 1],
    ], dtype=torch.bool)
    assert torch.equal(tree.ancestor_mask(), expected)


def test_different_first_tokens_are_separate_roots() -> None:
    tree = TokenTree.of([[7, 1], [8, 1]])
    assert tree.parents == [-1, 0, -1, 2]


def test_groups_bound_the_tokens_of_one_pass() -> None:
    assert groups([[1, 2], [3], [4, 5, 6], [7]], max_nodes=3) == [[0, 1], [2], [3]]
    assert groups([[1, 2, 3, 4]], max_nodes=2) == [[0]]  # a longer tail still gets a pass of its own
