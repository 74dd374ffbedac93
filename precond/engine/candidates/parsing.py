"""Model samples → normalised assertion expressions.

A sample is whatever the model wrote after the prompt's final `assert`: one assertion, several (`assert a`
on following lines), an assertion with a message, or text with trailing junk. Normalising with `ast.unparse`
and splitting top-level `and` lets equal candidates dedupe before they cost sandbox time; splitting is safe
because the preconditions of an action are a conjunction anyway.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable
from dataclasses import dataclass, field

MAX_TRIM = 40


@dataclass
class ParsedSamples:
    assertions: list[str] = field(default_factory=list)
    votes: dict[str, int] = field(default_factory=dict)  # how many samples proposed each assertion
    sampled: int = 0
    syntax_errors: int = 0


def _parse_prefix(text: str) -> ast.Module | None:
    """The longest parseable prefix: whole text, then whole lines, then the first line trimmed from the right."""
    candidates = [text]
    lines = text.splitlines()
    candidates += ["\n".join(lines[:n]) for n in range(len(lines) - 1, 0, -1)]
    first = lines[0] if lines else ""
    candidates += [first[:-cut] for cut in range(1, min(MAX_TRIM, len(first)))]
    for candidate in candidates:
        try:
            return ast.parse(candidate)
        except (SyntaxError, ValueError, RecursionError, MemoryError):
            continue
    return None


def _conjuncts(test: ast.expr) -> Iterable[ast.expr]:
    if isinstance(test, ast.BoolOp) and isinstance(test.op, ast.And):
        for value in test.values:
            yield from _conjuncts(value)
    else:
        yield test


def assertions_in(sample: str) -> list[str] | None:
    """The assertion expressions of one sample, or None when nothing in it parses."""
    text = "assert" + sample if not sample.lstrip().startswith("assert") else sample.lstrip()
    module = _parse_prefix(_dedent_continuations(text))
    if module is None:
        return None
    found = [
        ast.unparse(conjunct)
        for stmt in module.body
        if isinstance(stmt, ast.Assert)
        for conjunct in _conjuncts(stmt.test)
    ]
    return found or None


def _dedent_continuations(text: str) -> str:
    """Later `assert` lines keep the method's indentation; strip it so they parse as module statements."""
    lines = text.splitlines()
    return "\n".join([lines[0], *(line.strip() if line.strip().startswith("assert") else line for line in lines[1:])])


def parse_samples(samples: Iterable[str]) -> ParsedSamples:
    out = ParsedSamples()
    seen: set[str] = set()
    for sample in samples:
        out.sampled += 1
        found = assertions_in(sample)
        if found is None:
            out.syntax_errors += 1
            continue
        for expression in dict.fromkeys(found):
            out.votes[expression] = out.votes.get(expression, 0) + 1
            if expression not in seen:
                seen.add(expression)
                out.assertions.append(expression)
    return out
