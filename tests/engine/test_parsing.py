from precond.engine.candidates.parsing import assertions_in, parse_samples


def test_single_assertion_is_normalised() -> None:
    assert assertions_in(" self.user.requested_slot[ slot ]") == ["self.user.requested_slot[slot]"]


def test_message_is_dropped_and_conjunction_split() -> None:
    assert assertions_in(" a and (b or c), 'msg'") == ["a", "b or c"]


def test_several_asserts_and_trailing_junk() -> None:
    sample = " x is None\n        assert y == 1\n    def other(self):"
    assert assertions_in(sample) == ["x is None", "y == 1"]


def test_unbalanced_tail_is_trimmed() -> None:
    assert assertions_in(" self.x)") == ["self.x"]


def test_garbage_counts_as_syntax_error_and_duplicates_collapse() -> None:
    parsed = parse_samples([" a", " (a)", " ((", " b and a"])
    assert parsed.assertions == ["a", "b"]
    assert (parsed.sampled, parsed.syntax_errors) == (4, 1)


def test_votes_count_samples_not_occurrences() -> None:
    parsed = parse_samples([" a and a", " a", " b"])
    assert parsed.votes == {"a": 2, "b": 1}
