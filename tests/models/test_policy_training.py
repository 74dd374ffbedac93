"""Behaviour cloning (`precond train-policy`): LoRA training on the action lines, the adapter on disk, and an
adapter loaded only when it is exactly what this model can take. The tiny random model stands in for the real
one: what is asserted is the plumbing and the refusals, not the quality (bench/ and docs/results.md)."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import pytest
import torch
from pydantic import ValidationError
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from precond.cli.main import app
from precond.engine.acting.training import action_spans, closing_head, train_policy, turn_ends
from precond.engine.models import Sampling
from precond.engine.models import weights as weights_module
from precond.engine.models.adapters import RESULT, WEIGHTS, AdapterError, read_result
from precond.engine.models.backend import load_code_model, with_adapter
from precond.engine.models.weights import Weights, load_weights
from precond.engine.settings import ModelSettings
from precond.engine.spec import parse_spec
from precond_client.schemas.errors import Cancelled, InvalidInput
from precond_client.schemas.training import MAX_TRAINING_STEPS, TrainPolicyOptions, TrainPolicyRequest

SPEC = """from collections import defaultdict
class USER:
  def __init__(self):
    self.informed_slot = defaultdict(lambda: False)
  def INFORM(self, slot): self.informed_slot[slot] = True

class SYSTEM:
  def __init__(self, user):
    self.user = user
  def REQUEST(self, slot): pass
  def GOODBYE(self): pass
"""
DEMO = ("user = USER()\nsystem = SYSTEM(user)\nsystem.REQUEST('city')\nuser.INFORM('city')\n"
        "system.REQUEST('date')\nuser.INFORM('date')\nsystem.GOODBYE()\n")


def _settings(tiny_model_dir: Path, quant: str = "none") -> ModelSettings:
    return ModelSettings(path=str(tiny_model_dir), device="cpu", dtype="float32", threads=1, quant=quant)


def _request(steps: int = 3, demos: list[str] | None = None, **options: object) -> TrainPolicyRequest:
    return TrainPolicyRequest(spec=SPEC, demonstrations=demos or [DEMO],
                              options=TrainPolicyOptions(steps=steps, **options))  # type: ignore[arg-type]


def _train(tiny_model_dir: Path, out: Path, request: TrainPolicyRequest, cancelled: bool = False) -> object:
    return train_policy(lambda: load_weights(_settings(tiny_model_dir)), parse_spec(request.spec), request, out,
                        lambda *_: None, lambda: cancelled)


def test_the_loss_is_taken_on_the_action_lines_and_where_the_turn_ends() -> None:
    spans = action_spans(parse_spec(SPEC), DEMO, 0)
    assert [DEMO[a:b] for a, b in spans] == ["system.REQUEST('city')\n", "system.REQUEST('date')\n",
                                             "system.GOODBYE()\n"]
    assert [DEMO[a:b] for a, b in turn_ends(DEMO, spans)] == ["user.INFORM", "user.INFORM"]
    # the dialog ends on the agent's GOODBYE: its turn ends too, with the other party's name after it
    assert closing_head(parse_spec(SPEC), DEMO, spans) == "user"
    assert closing_head(parse_spec(SPEC), DEMO + "user.INFORM('x')\n", spans) is None


def test_the_dialogs_end_is_trained_as_a_turn_end(tiny_model_dir: Path) -> None:
    """After the closing GOODBYE the policy learns to hand over (`user`), not to say it again."""
    from precond.engine.acting.training import action_lines, examples

    spec = parse_spec(SPEC)
    tokenizer = load_weights(_settings(tiny_model_dir)).tokenizer
    [example] = examples(tokenizer, 0, [DEMO], spec, action_lines(spec, [DEMO]), 4096)
    assert tokenizer.decode(example.ids).endswith("system.GOODBYE()\nuser")
    closing = [k for k in example.targets if k >= len(example.ids) - len(tokenizer("user")["input_ids"])]
    assert tokenizer.decode([example.ids[k] for k in closing]) == "user"


def test_training_lowers_the_loss_and_writes_a_loadable_adapter(tiny_model_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "bc"
    result = _train(tiny_model_dir, out, _request(steps=30, learning_rate=1e-2))
    stored = read_result(out)
    assert stored == result
    assert stored.steps == 30 and stored.examples == 1 and stored.action_lines == 3 and stored.truncated == 0
    assert stored.calls == ["system.REQUEST('city')", "system.REQUEST('date')", "system.GOODBYE()"]
    assert sum(stored.losses[-5:]) < sum(stored.losses[:5])  # it learned the three calls
    assert 0 < stored.adapter_bytes == (out / WEIGHTS).stat().st_size
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bc"]  # no scratch directory left behind

    base = load_code_model(_settings(tiny_model_dir))
    tuned = load_code_model(_settings(tiny_model_dir), out)
    assert base.info.adapter is None and tuned.info.adapter is not None and tuned.info.adapter.startswith("bc@")
    ids = base.tokenizer(SPEC + "\n# Current\n" + DEMO, return_tensors="pt")["input_ids"]
    with torch.no_grad():
        assert not torch.allclose(base.model(ids).logits, tuned.model(ids).logits)
    assert not any("lora" in name for name, _ in tuned.model.named_parameters())  # merged, nothing left over


def test_demonstrations_without_action_lines_are_refused_before_a_model_is_loaded(tmp_path: Path) -> None:
    def load() -> Weights:
        raise AssertionError("the model was loaded for a request with nothing to learn")

    request = _request(demos=["user = USER()\nsystem = SYSTEM(user)\nuser.INFORM('city')\n"])
    with pytest.raises(InvalidInput) as caught:
        train_policy(load, parse_spec(SPEC), request, tmp_path / "bc", lambda *_: None, lambda: False)
    assert caught.value.field == "demonstrations"
    assert not (tmp_path / "bc").exists()


def test_a_cancelled_training_leaves_no_adapter(tiny_model_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(Cancelled):
        _train(tiny_model_dir, tmp_path / "bc", _request(), cancelled=True)
    assert list(tmp_path.iterdir()) == []


def test_steps_beyond_the_bound_are_refused_naming_the_field(tmp_path: Path) -> None:
    with pytest.raises(ValidationError) as caught:
        TrainPolicyOptions(steps=MAX_TRAINING_STEPS + 1)
    assert caught.value.errors()[0]["loc"] == ("steps",)
    body = tmp_path / "train.json"
    body.write_text(json.dumps({"spec": SPEC, "demonstrations": [DEMO], "options": {"steps": 10_000}}))
    result = CliRunner().invoke(app, ["train-policy", str(body), "--out", str(tmp_path / "bc")])
    assert result.exit_code == 2 and "options.steps" in result.output
    assert not (tmp_path / "bc").exists()


def test_a_stored_policy_named_in_process_is_refused_not_ignored(tmp_path: Path) -> None:
    """`options.policy` names a policy stored in the service; run in-process, the base model would answer in its
    place: refused before any model is loaded, saying what to do instead."""
    body = tmp_path / "next.json"
    body.write_text(json.dumps({"spec": SPEC, "history": DEMO, "options": {"policy": "adapter:ad_" + "1" * 24}}))
    result = CliRunner().invoke(app, ["next-action", str(body)])
    assert result.exit_code == 2 and "options.policy" in result.output and "--server" in result.output


@pytest.fixture
def adapter(tiny_model_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("adapters") / "bc"
    _train(tiny_model_dir, out, _request(steps=1))
    return out


def test_an_adapter_of_another_base_model_is_refused(tiny_model_dir: Path, adapter: Path) -> None:
    stored = read_result(adapter)
    (adapter / RESULT).write_text(stored.model_copy(update={"base_model": "another-model"}).model_dump_json())
    with pytest.raises(AdapterError, match="trained on another-model"):
        load_code_model(_settings(tiny_model_dir), adapter)


def test_weights_that_do_not_fit_are_refused(tiny_model_dir: Path, adapter: Path) -> None:
    tensors = load_file(adapter / WEIGHTS)
    tensors["base_model.model.lm_head.lora_A.weight"] = torch.zeros(8, 64)  # a layer the policy never trains
    save_file(tensors, adapter / WEIGHTS)
    with pytest.raises(AdapterError, match="does not fit this model"):
        load_code_model(_settings(tiny_model_dir), adapter)


def test_a_pickle_in_place_of_the_weights_is_refused_unread(tiny_model_dir: Path, adapter: Path) -> None:
    torch.save({"x": torch.zeros(1)}, adapter / WEIGHTS)  # torch.save writes a pickle: never loaded as one
    with pytest.raises(AdapterError, match="not a safetensors file"):
        load_code_model(_settings(tiny_model_dir), adapter)


def test_an_adapted_copy_answers_as_a_loaded_adapter_and_leaves_the_base_as_it_was(tiny_model_dir: Path,
                                                                                   adapter: Path) -> None:
    """What a worker serves for a tenant's policy (`with_adapter`: the adapter beside the projections, unmerged,
    every weight shared) is the model `load_code_model(adapter)` loads (merged), and the served base model is
    not touched by it, bit for bit."""
    base = load_code_model(_settings(tiny_model_dir))
    before = {name: t.clone() for name, t in base.model.state_dict().items()}
    adapted = with_adapter(base, adapter)
    loaded = load_code_model(_settings(tiny_model_dir), adapter)
    ids = base.tokenizer(SPEC + "\n# Current\n" + DEMO, return_tensors="pt")["input_ids"]
    with torch.no_grad():
        assert torch.allclose(adapted.model(ids).logits, loaded.model(ids).logits, atol=1e-4)  # merged: other sums
        assert not torch.allclose(adapted.model(ids).logits, base.model(ids).logits)
    assert all(torch.equal(before[name], t) for name, t in base.model.state_dict().items())
    assert adapted.info.adapter == loaded.info.adapter and adapted.known_calls == loaded.known_calls
    base_tensors = {t.data_ptr() for t in [*base.model.parameters(), *base.model.buffers()]}
    own = {n for n, t in [*adapted.model.named_parameters(), *adapted.model.named_buffers()]
           if t.data_ptr() not in base_tensors}
    assert own and all(n.rsplit(".", 1)[-1] in ("a", "b") for n in own)  # only the adapter's tensors are new
    assert all(t.data_ptr() in base_tensors for t in adapted.model.parameters())


def test_an_adapter_runs_beside_int8_weights(tiny_model_dir: Path, adapter: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """An int8 base cannot take a merge; the unmerged adapter over it moves its answers toward the merged
    full-width model's (the rest of the gap is int8's own error on this random tiny model)."""
    monkeypatch.setattr(weights_module, "cpu_flags", lambda: frozenset({"avx2", "avx512_vnni"}))
    small = load_code_model(_settings(tiny_model_dir, "int8"))
    adapted, loaded = with_adapter(small, adapter), load_code_model(_settings(tiny_model_dir), adapter)
    ids = small.tokenizer(SPEC + "\n# Current\n" + DEMO, return_tensors="pt")["input_ids"]
    with torch.no_grad():
        ours, merged, plain = (m.model(ids).logits for m in (adapted, loaded, small))
    assert (ours - merged).norm() < (plain - merged).norm()  # the adapter acts, toward what the merge gives
    assert adapted.info.quant == "int8" and adapted.info.adapter == loaded.info.adapter


def test_an_adapted_copy_keeps_its_prompt_prefixes_apart_in_the_base_models_store(tiny_model_dir: Path,
                                                                                   adapter: Path) -> None:
    """The adapter changes the keys and values, so its prefixes are its own; they count against the base model's
    one token bound, and a second request of the adapter reuses its first's."""
    base = load_code_model(_settings(tiny_model_dir))
    adapted = with_adapter(base, adapter)
    assert adapted._prefixes is base._prefixes
    sampling = Sampling(temperature=0, max_new_tokens=4)
    first = adapted.complete(SPEC, ["\nsystem."], 1, sampling, "line")
    base.complete(SPEC, ["\nsystem."], 1, sampling, "line")
    assert len(base._prefixes.scopes()) == 2
    assert adapted.complete(SPEC, ["\nsystem."], 1, sampling, "line") == first


def test_next_action_with_an_adapter_keeps_it_unmerged_as_the_service_does(
    tiny_model_dir: Path, adapter: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`precond next-action --adapter` predicts with the adapter beside the weights (`with_adapter`), the path a
    worker serves, never merging it: the answer names the adapter and no merge runs."""
    from precond.engine.models import adapters

    def no_merge(*_: object) -> None:
        raise AssertionError("the adapter was merged")

    monkeypatch.setattr(adapters, "merge_adapter", no_merge)
    for name, value in {"MODEL_PATH": str(tiny_model_dir), "MODEL_DEVICE": "cpu", "MODEL_DTYPE": "float32",
                        "MODEL_QUANT": "none"}.items():
        monkeypatch.setenv(name, value)
    body = tmp_path / "next.json"
    body.write_text(json.dumps({"spec": SPEC, "history": DEMO.rsplit("system.", 1)[0],
                                "options": {"max_new_tokens": 4}}))
    result = CliRunner().invoke(app, ["next-action", str(body), "--adapter", str(adapter)])
    assert result.exit_code == 0, result.output
    answer = json.loads(result.stdout)
    assert answer["model"]["adapter"].startswith("bc@")


def test_training_and_loading_an_adapter_warn_of_nothing(tiny_model_dir: Path, tmp_path: Path) -> None:
    """peft read transformers' deprecated `is_gradient_checkpointing` in every training and adapter load: a
    FutureWarning in the worker's log about code that is not ours."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)
        _train(tiny_model_dir, tmp_path / "bc", _request(steps=2))
        load_code_model(_settings(tiny_model_dir), tmp_path / "bc")
