"""`precond convert sgd|events`: SGD's own file format and generic JSON events → spec, programs, request.

The SGD input is a made-up service (tests/fixtures/sgd_raw/, Library_1); the development fixtures'
dialogues (tests/fixtures/data/sgd/) are rebuilt in SGD's raw shape from their recorded steps, and the
converter must give back their programs line for line.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from precond.convert import events as events_converter
from precond.convert import sgd as sgd_converter
from precond_client.schemas import InferRequest
from tests.cli.inprocess import precond

ROOT = Path(__file__).resolve().parents[2]
RAW = ROOT / "tests" / "fixtures" / "sgd_raw"
DATA = ROOT / "tests" / "fixtures" / "data" / "sgd"


def test_sgd_files_become_spec_demonstrations_and_a_request_the_engine_runs(tmp_path: Path) -> None:
    done = precond("convert", "sgd", str(RAW / "schema.json"), str(RAW / "dialogues_001.json"),
                   "--service", "Library_1", "--out", str(tmp_path))
    assert done.returncode == 0, done.stderr
    assert "2 dialogues" in done.stderr and "1 skipped" in done.stderr
    spec = (tmp_path / "spec.py").read_text()
    assert "  def FindBooks(self): pass" in spec and "  def BorrowBook(self): pass" in spec
    assert "OrderDrink" not in spec
    found = (tmp_path / "demos" / "1_00001.py").read_text().splitlines()
    assert found == ["user = USER()", "system = SYSTEM(user)", "user.INFORM_INTENT('FindBooks')",
                     "system.REQUEST('author')", "user.INFORM('author')", "system.FindBooks()",
                     "system.set_query_status(False)", "system.REQ_MORE()", "user.GOODBYE()", "system.GOODBYE()"]
    borrowed = (tmp_path / "demos" / "1_00000.py").read_text()
    assert "system.BorrowBook()\nsystem.set_query_status(True)\nsystem.NOTIFY_SUCCESS()\n" in borrowed
    request = InferRequest.model_validate_json((tmp_path / "request.json").read_text())
    assert request.spec == spec and len(request.demonstrations) == 2

    body = request.model_dump(mode="json")
    # two dialogues: every action occurs once or twice, too thin for evidence-weighted validation to learn
    # from, so the paper's strict validation (tolerance 0) shows what the converter's programs carry
    body["options"] = {"generators": ["enumerate"], "tolerance": 0}
    inferred = precond("infer", "-", stdin=json.dumps(body))  # the engine runs what the converter wrote
    assert inferred.returncode == 0, inferred.stderr
    answer = json.loads(inferred.stdout)
    assert "self.user.informed_slot['author']" in answer["preconditions"]["SYSTEM.FindBooks"]
    assert "self.query_success" in answer["preconditions"]["SYSTEM.OFFER"]  # from the service call's results
    assert answer["warnings"]["SYSTEM.NOTIFY_FAILURE"].startswith("no occurrence")


def test_a_schema_with_several_services_needs_one_named(tmp_path: Path) -> None:
    done = precond("convert", "sgd", str(RAW / "schema.json"), str(RAW / "dialogues_001.json"),
                   "--out", str(tmp_path))
    assert done.returncode == 2 and "--service" in done.stderr and "Library_1" in done.stderr


def test_a_file_of_the_wrong_shape_names_the_file_and_the_key(tmp_path: Path) -> None:
    bad = RAW / "dialogues_bad.json"
    done = precond("convert", "sgd", str(RAW / "schema.json"), str(bad), "--service", "Library_1",
                   "--out", str(tmp_path))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"{bad}: [0].turns[1].frames[0]: missing key 'actions'" in done.stderr
    swapped = precond("convert", "sgd", str(bad), str(RAW / "dialogues_001.json"), "--out", str(tmp_path))
    assert swapped.returncode == 2 and f"{bad}: [0]: missing key 'service_name'" in swapped.stderr


def _raw_dialogue(demo: dict[str, Any], service: str) -> dict[str, Any]:
    """A development fixture's dialogue back in SGD's raw shape, from its recorded steps and turns."""
    steps = demo["steps"]
    turns = []
    for turn in demo["turns"]:
        frame: dict[str, Any] = {"service": service, "slots": [], "actions": []}
        for step in steps[turn["steps"][0]:turn["steps"][1]]:
            if step["kind"] == "service_call":
                frame["service_call"] = {"method": step["act"], "parameters": {}}
            elif step["kind"] == "query_status":
                frame["service_results"] = [{}] if step["arg"] else []
            elif step["act"] in ("INFORM_INTENT", "OFFER_INTENT"):
                frame["actions"].append({"act": step["act"], "slot": "intent", "values": [step["arg"]]})
            else:
                frame["actions"].append({"act": step["act"], "slot": step["arg"] or "", "values": []})
        turns.append({"speaker": turn["speaker"], "utterance": turn["utterance"], "frames": [frame]})
    return {"dialogue_id": demo["dialogue_id"], "services": [service], "turns": turns}


@pytest.mark.parametrize("service", ["Restaurants_1", "Events_1"])
def test_sgd_conversion_gives_back_the_development_programs(tmp_path: Path, service: str) -> None:
    data = json.loads((DATA / f"{service}.json").read_text())
    schema = [{"service_name": service, "slots": [{"name": s} for s in data["slots"]],
               "intents": [{"name": i["name"]} for i in data["intents"]]}]
    (tmp_path / "schema.json").write_text(json.dumps(schema))
    (tmp_path / "dialogues.json").write_text(json.dumps([_raw_dialogue(d, service) for d in data["demos"]]))
    converted = sgd_converter.convert(tmp_path / "schema.json", [tmp_path / "dialogues.json"], None)
    assert list(converted.demonstrations.values()) == [d["program"] for d in data["demos"]]


def test_events_become_a_program_with_safe_literals(tmp_path: Path) -> None:
    data = json.loads((DATA / "Events_1.json").read_text())
    (tmp_path / "spec.py").write_text(data["spec_program"])
    runs = [[{"actor": s["actor"], "act": s["act"], "args": [] if s["arg"] is None else [s["arg"]]}
             for s in demo["steps"]] for demo in data["demos"][:3]]
    (tmp_path / "events.json").write_text(json.dumps(runs))
    _, programs = events_converter.convert(tmp_path / "events.json", tmp_path / "spec.py")
    assert programs == [d["program"] for d in data["demos"][:3]]

    (tmp_path / "one.json").write_text(json.dumps(runs[0]))
    printed = precond("convert", "events", str(tmp_path / "one.json"), "--spec", str(tmp_path / "spec.py"))
    assert printed.returncode == 0, printed.stderr
    assert printed.stdout.strip() == data["demos"][0]["program"].strip()
    written = precond("convert", "events", str(tmp_path / "events.json"), "--spec", str(tmp_path / "spec.py"),
                      "--request", str(tmp_path / "request.json"))
    assert written.returncode == 0, written.stderr
    assert len(InferRequest.model_validate_json((tmp_path / "request.json").read_text()).demonstrations) == 3


@pytest.mark.parametrize(("event", "says"), [
    ({"actor": "user", "act": "INFORM", "args": [{"__class__": "x"}]}, "[1].args[0]: dict"),
    ({"actor": "user", "act": "INFORM", "args": ["x'); import os; os.system('id'); ('"]}, None),
    ({"actor": "user", "act": "DANCE"}, "[1]: unknown act 'DANCE' of user (USER)"),
    ({"actor": "user", "act": "INFROM", "args": ["city"]}, "(did you mean 'INFORM'?)"),
    ({"actor": "user", "act": "INFORM", "args": ["city", "Paris"]},
     "[1]: USER.INFORM takes 1 argument(s) (slot), got 2"),
    ({"actor": "os", "act": "system", "args": ["id"]}, "[1]: unknown actor 'os'"),
    ({"actor": "user", "act": "INFORM", "arg": "city"}, "[1]: unknown key 'arg'"),
])
def test_events_refuse_what_is_not_a_call_of_the_spec(tmp_path: Path, event: dict[str, Any], says: str | None
                                                      ) -> None:
    (tmp_path / "spec.py").write_text(json.loads((DATA / "Events_1.json").read_text())["spec_program"])
    (tmp_path / "events.json").write_text(json.dumps([{"actor": "user", "act": "GOODBYE"}, event]))
    done = precond("convert", "events", str(tmp_path / "events.json"), "--spec", str(tmp_path / "spec.py"))
    if says is None:  # a hostile string stays a string: one call, its argument the literal text
        assert done.returncode == 0, done.stderr
        last = done.stdout.strip().splitlines()[-1]
        assert last == "user.INFORM(" + repr(event["args"][0]) + ")"
        assert len(done.stdout.strip().splitlines()) == 4
    else:
        assert done.returncode == 2 and says in done.stderr and str(tmp_path / "events.json") in done.stderr


def test_a_spec_file_and_demonstration_files_become_an_infer_request(tmp_path: Path) -> None:
    example = json.loads((ROOT / "examples" / "infer-enumerate.json").read_text())
    (tmp_path / "demos").mkdir()
    (tmp_path / "spec.py").write_text(example["spec"])
    paths = []
    for index, demo in enumerate(example["demonstrations"]):
        paths.append(tmp_path / "demos" / f"d{index}.py")
        paths[-1].write_text(demo)
    done = precond("convert", "programs", "--spec", str(tmp_path / "spec.py"), *map(str, paths))
    assert done.returncode == 0, done.stderr
    body = InferRequest.model_validate_json(done.stdout)
    assert body.spec == example["spec"] and body.demonstrations == example["demonstrations"]
    written = precond("convert", "programs", "--spec", str(tmp_path / "spec.py"), *map(str, paths),
                      "--request", str(tmp_path / "request.json"))
    assert written.returncode == 0 and InferRequest.model_validate_json((tmp_path / "request.json").read_text())
    paths[1].write_text(example["demonstrations"][1] + "system.REQUEST('city'\n")
    broken = precond("convert", "programs", "--spec", str(tmp_path / "spec.py"), *map(str, paths))
    assert broken.returncode == 2 and f"error: {paths[1]}: demonstrations[1], line " in broken.stderr
    assert "SyntaxError" in broken.stderr


@pytest.mark.parametrize("intent", ["ＩＮＦＯＲＭ", "ｓｅｔ_ｑｕｅｒｙ_ｓｔａｔｕｓ", "ｉｆ"])
def test_an_intent_is_checked_as_python_reads_its_name(tmp_path: Path, intent: str) -> None:
    """`def ＩＮＦＯＲＭ(self)` defines `INFORM` (Python reads names NFKC-normalised): an intent so named would
    replace SYSTEM's own act."""
    schema = tmp_path / "schema.json"
    schema.write_text(json.dumps([{"service_name": "Shop_1", "slots": [], "intents": [{"name": intent}]}]))
    dialogues = tmp_path / "dialogues.json"
    dialogues.write_text("[]")
    with pytest.raises(sgd_converter.ConvertError, match=r"intents\[0\]\.name: .* cannot be a method of SYSTEM"):
        sgd_converter.convert(schema, [dialogues], None)
