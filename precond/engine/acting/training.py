"""Behaviour cloning: LoRA fine-tuning of the code model on the demonstrations' action lines.

Each example is what the policy sees at next-action time with no few-shot demonstration (the spec, `# Current`,
then the dialog: `engine.prompting.next_action_prompt`), so the adapter learns to continue exactly that prompt.
The loss is on the action lines (the calls the acting class makes, as `engine.next_action.classify` reads
them) and on the head of the line that ends each turn (`user.INFORM`, `system.set_query_status`: when to stop
acting is behaviour too), the dialog's last turn included: a demonstration that ends on the agent's turn gets
the other party's name after it (`user`), the head the next-action modes score the turn's end by, so that a
cloned policy stops after its closing `GOODBYE()` instead of saying it again. The rest of the users' turns and
the service answers are context, not behaviour to clone. The spec is the same in every example, so its keys
and values are computed once per step without gradients and only the dialog is trained through; the logits
are computed only where a loss is taken (the 150k-token vocabulary is a quarter of the work otherwise).

Demonstrations are untrusted text, but nothing here runs them: they are parsed (`ast`) and tokenized.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from precond.engine.acting.next_action import classify
from precond.engine.candidates import prompting
from precond.engine.models.adapters import save_adapter, with_lora
from precond.engine.models.weights import Weights
from precond.engine.spec import Spec, parse_source
from precond.programs.checks import instance_classes
from precond_client.schemas import MAX_CALL_CHARS
from precond_client.schemas.errors import Cancelled, InvalidInput
from precond_client.schemas.training import (
    MAX_KNOWN_CALLS,
    TrainPolicyOptions,
    TrainPolicyRequest,
    TrainPolicyResult,
)

ProgressFn = Callable[[str, int, int], None]
OBJECTIVE = "action lines and turn ends (the dialog's end included), spec prefix without gradients"
"""What the loss is taken on; stored with every adapter, and part of the evaluation's adapter key."""


@dataclass(frozen=True)
class Example:
    ids: list[int]
    """The dialog's tokens (after the shared spec prefix)."""
    targets: list[int]
    """Indices into `ids` of the tokens the loss is taken on (action lines, turn ends): each is predicted from
    everything before it."""
    truncated: bool


def action_spans(spec: Spec, demonstration: str, index: int) -> list[tuple[int, int]]:
    """Character spans (start of line, end of line with its newline) of the demonstration's action calls."""
    tree = parse_source(demonstration, f"demonstrations[{index}]")
    receivers = instance_classes([tree], {m.cls for m in spec.methods.values()})
    actions = set(spec.stub_actions)
    spans, start = [], 0
    for line in demonstration.splitlines(keepends=True):
        if classify(line, receivers, actions).call is not None:  # one call of an action, nothing else
            spans.append((start, start + len(line)))
        start += len(line)
    return spans


def turn_ends(demonstration: str, spans: Sequence[tuple[int, int]]) -> list[tuple[int, int]]:
    """After each run of action lines, the head of the line that ends the turn (`user.INFORM`,
    `system.set_query_status`): where the policy must stop acting, which the next-action modes read from
    these heads' likelihood (`engine.constrained.turn_heads`)."""
    starts = {a for a, _ in spans}
    ends = []
    for _, end in spans:
        if end in starts or end >= len(demonstration):
            continue
        line = demonstration[end:].split("\n", 1)[0]
        head = line.split("(", 1)[0]
        if head.strip():
            ends.append((end, end + len(head)))
    return ends


def closing_head(spec: Spec, demonstration: str, spans: Sequence[tuple[int, int]]) -> str | None:
    """The other party's name (`user`) when the demonstration ends on the agent's turn: the head its last turn
    would end with, had the dialog gone on (the party that ends most of its other turns). None when the
    demonstration ends on something other than an action, or no other party exists."""
    if not spans or demonstration[spans[-1][1]:].strip():
        return None
    tree = parse_source(demonstration, "demonstration")
    acting = {spec.methods[a].cls for a in spec.stub_actions}
    others = [var for var, cls in instance_classes([tree], {m.cls for m in spec.methods.values()}).items()
              if cls not in acting]
    if not others:
        return None
    heads = [demonstration[a:b].split(".", 1)[0] for a, b in turn_ends(demonstration, spans)]
    return max(others, key=lambda var: (heads.count(var), -others.index(var)))


def known_calls(demonstrations: Sequence[str], lines: Sequence[Sequence[tuple[int, int]]]) -> list[str]:
    """The distinct action calls the training showed, first seen first, at most MAX_KNOWN_CALLS."""
    calls = dict.fromkeys(demo[a:b].strip() for demo, spans in zip(demonstrations, lines, strict=True)
                          for a, b in spans if b - a <= MAX_CALL_CHARS)
    return list(calls)[:MAX_KNOWN_CALLS]


def split_prompt(spec: Spec, demonstration: str) -> tuple[str, str]:
    """The next-action prompt with the whole demonstration as its history, split where the history begins."""
    prompt = prompting.next_action_prompt(spec, {}, [], demonstration, with_preconditions=False)
    start = len(prompt) - len(demonstration.rstrip()) - 1
    return prompt[:start], prompt[start:]


def action_lines(spec: Spec, demonstrations: Sequence[str]) -> list[list[tuple[int, int]]]:
    """Each demonstration's action lines; refuses demonstrations without any (nothing to learn: 422 naming the
    field), before a model is loaded."""
    spans = [action_spans(spec, demo, i) for i, demo in enumerate(demonstrations)]
    if not any(spans):
        raise InvalidInput("no demonstration has an action line (a call of the spec's action functions on an "
                           "object of their class, e.g. `system.REQUEST('city')`): there is no behaviour to "
                           "learn", field="demonstrations")
    return spans


def examples(tokenizer: Any, prefix_tokens: int, demonstrations: Sequence[str], spec: Spec,
             lines: Sequence[Sequence[tuple[int, int]]], max_tokens: int) -> list[Example]:
    """The tokenized dialogs (prefix excluded), each with the tokens of its action lines."""
    out = []
    for demo, spans in zip(demonstrations, lines, strict=True):
        text = split_prompt(spec, demo)[1]
        trained = [*spans, *turn_ends(demo, spans)]
        head = closing_head(spec, demo, spans)
        if head is not None:
            trained.append((len(text), len(text) + len(head)))
            text += head
        encoded = tokenizer(text, return_offsets_mapping=True, add_special_tokens=False)
        ids, offsets = encoded["input_ids"], encoded["offset_mapping"]
        keep = min(len(ids), max(0, max_tokens - prefix_tokens))
        # the first token is predicted from the spec's last logit, which is computed without gradients
        targets = [k for k, (a, _) in enumerate(offsets[:keep]) if k and any(s <= a < e for s, e in trained)]
        if targets:
            out.append(Example(ids[:keep], targets, keep < len(ids)))
    if not out:
        raise InvalidInput(f"every action line lies beyond options.max_tokens ({max_tokens} tokens with the spec)",
                           field="options.max_tokens")
    return out


def train_policy(load: Callable[[], Weights], spec: Spec, request: TrainPolicyRequest, out: Path,
                 progress: ProgressFn, cancelled: Callable[[], bool]) -> TrainPolicyResult:
    """Check the request, load the model, train, then save the adapter at `out` (only when every step ran: a
    cancelled training saves nothing)."""
    options = request.options
    lines = action_lines(spec, request.demonstrations)
    start = time.perf_counter()
    weights = load()
    prefix = split_prompt(spec, request.demonstrations[0])[0]
    prefix_list = weights.tokenizer(prefix, add_special_tokens=False)["input_ids"]
    found = examples(weights.tokenizer, len(prefix_list), request.demonstrations, spec, lines, options.max_tokens)
    torch.manual_seed(options.seed)
    model = with_lora(weights.model, options.rank)
    prefix_ids = torch.tensor([prefix_list], device=weights.device)
    losses = _fit(model, prefix_ids, _schedule(found, options.steps, options.seed), options, progress, cancelled)
    progress("train", options.steps, options.steps)
    result = TrainPolicyResult(
        calls=known_calls(request.demonstrations, lines), objective=OBJECTIVE,
        base_model=weights.info.name, base_sha256=weights.info.sha256, dtype=weights.info.dtype,
        steps=options.steps, examples=len(found), action_lines=sum(map(len, lines)),
        truncated=sum(e.truncated for e in found),
        losses=losses, seconds=round(time.perf_counter() - start, 1),
        trainable_parameters=sum(p.numel() for p in model.parameters() if p.requires_grad), adapter_bytes=0,
        options=options)
    return save_adapter(model, out, result)


def _fit(model: Any, prefix_ids: torch.Tensor, schedule: Sequence[Example], options: TrainPolicyOptions,
         progress: ProgressFn, cancelled: Callable[[], bool]) -> list[float]:
    """One example per AdamW step, the learning rate decaying linearly to a tenth (late steps refine, not
    overwrite); the loss of each step."""
    model.train()
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(trainable, lr=options.learning_rate, weight_decay=0.0)
    losses = []
    for step, example in enumerate(schedule):
        if cancelled():
            raise Cancelled("the training was cancelled; no adapter was saved")
        progress("train", step, len(schedule))
        for group in optimizer.param_groups:
            group["lr"] = options.learning_rate * (1 - 0.9 * step / max(1, len(schedule) - 1))
        loss = _loss(model, prefix_ids, example, prefix_ids.device)
        if not math.isfinite(loss.item()):
            raise InvalidInput(f"the training diverged: the loss at step {step + 1} is {loss.item()}, so no "
                               "adapter was saved (a lower options.learning_rate may help)",
                               field="options.learning_rate")
        loss.backward()  # type: ignore[no-untyped-call]
        torch.nn.utils.clip_grad_norm_(trainable, 1.0)
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        losses.append(round(loss.item(), 4))
    return losses


def _schedule(found: Sequence[Example], steps: int, seed: int) -> list[Example]:
    """Every example once (seeded order) before any repeats."""
    rng, order = random.Random(seed), list[Example]()
    while len(order) < steps:
        epoch = list(found)
        rng.shuffle(epoch)
        order += epoch
    return order[:steps]


def _loss(model: Any, prefix_ids: torch.Tensor, example: Example, device: torch.device) -> torch.Tensor:
    """Mean cross-entropy over the example's action tokens, the spec's cache computed without gradients."""
    with torch.no_grad():
        cache = model(input_ids=prefix_ids, use_cache=True).cache
    ids = torch.tensor([example.ids], device=device)
    # the logit at position k predicts token k+1; the first dialog token is predicted from the prefix's last
    positions = [t - 1 for t in example.targets]
    output = model(input_ids=ids, cache=cache, use_cache=False,
                   logits_to_keep=torch.tensor(positions, device=device))
    logits = output.logits[0].float()
    targets = ids[0, torch.tensor(positions, device=device) + 1]
    return torch.nn.functional.cross_entropy(logits, targets)
