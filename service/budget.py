"""The work budget of a request, estimated from its text before anything is queued.

Inference judges every candidate at every point of its action: demonstration steps × the distinct argument
tuples the action was called with. That product, not the body's size, is what costs: 37 KB of demonstrations
with 3,000 distinct calls make 9 million points. The gateway reads the demonstrations with `ast` (never runs
them), bounds the product, and answers 422 naming the field; the sandbox bounds the exact count again
inside its child (`SANDBOX_MAX_POINTS`).
"""

from __future__ import annotations

import ast
from collections import defaultdict

from pydantic import BaseModel

from programs import main_body
from schemas.api import InferRequest, NextActionRequest


class OverBudget(ValueError):
    def __init__(self, message: str, field: str) -> None:
        super().__init__(message)
        self.field = field


def check_work(body: BaseModel, budget: int) -> None:
    if isinstance(body, InferRequest | NextActionRequest):
        _check_points(body.demonstrations, budget)


def _check_points(demonstrations: list[str], budget: int) -> None:
    steps = 0
    arguments: dict[str, set[str]] = defaultdict(set)
    for source in demonstrations:
        try:
            tree = ast.parse(source)
        except (SyntaxError, ValueError, RecursionError, MemoryError):
            continue  # the engine names the line; only work that would run is counted here
        steps += len(main_body(tree))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                call = ast.Call(func=ast.Name("f"), args=node.args, keywords=node.keywords)
                arguments[node.func.attr].add(ast.dump(call))
    if not arguments:
        return
    method, values = max(arguments.items(), key=lambda item: len(item[1]))
    points = steps * len(values)
    if points > budget:
        raise OverBudget(
            f"about {points:,} points to judge every candidate at ({steps:,} demonstration steps x "
            f"{len(values):,} distinct argument tuples of .{method}(...)), over the budget of {budget:,} "
            "(PRECOND_MAX_WORK_POINTS): send fewer demonstrations or fewer distinct arguments",
            field="demonstrations",
        )
