"""Schema-Guided Dialogue (SGD) files → spec, demonstration programs and an infer request.

The rules (docs/converting.md): user dialog acts are observations (methods of USER that update its state),
system dialog acts and the service's intents are actions (stubs of SYSTEM), and a system turn's service call
becomes `system.<Intent>()` followed by `system.set_query_status(True|False)` from whether it returned results.
"""

from __future__ import annotations

import keyword
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from precond.convert.shape import ConvertError, expect, key, load_json
from precond.programs.names import python_name

USER_SPEC = '''from collections import defaultdict
class USER:
  def __init__(self):
    self.informed_intent = defaultdict(lambda: False)
    self.informed_slot = defaultdict(lambda: False)
    self.requested_slot = defaultdict(lambda: False)
    self.no_more = False
    self.selected = False
    self.affirmed = False
    self.affirm_intent = False
    self.negate_intent = False
    self.request_alternatives = False
  def INFORM_INTENT(self, intent): self.informed_intent[intent] = True
  def NEGATE_INTENT(self): self.negate_intent = True
  def AFFIRM_INTENT(self): self.affirm_intent = True
  def REQUEST_ALTS(self): self.request_alternatives = True
  def INFORM(self, slot): self.informed_slot[slot] = True
  def REQUEST(self, slot): self.requested_slot[slot] = True
  def GOODBYE(self): self.no_more = True
  def THANK_YOU(self): self.no_more = True
  def SELECT(self): self.selected = True
  def AFFIRM(self): self.affirmed = True
  def NEGATE(self): self.affirmed = False
'''

SLOT_ACTS = {"INFORM", "REQUEST", "CONFIRM", "OFFER"}
"""Acts whose argument is the act's slot (`user.INFORM('city')`, `system.OFFER('event_name')`)."""
INTENT_ACTS = {"INFORM_INTENT", "OFFER_INTENT"}
"""Acts whose argument is the intent, the act's first value (`user.INFORM_INTENT('FindEvents')`)."""
USER_ACTS = ("INFORM_INTENT", "NEGATE_INTENT", "AFFIRM_INTENT", "REQUEST_ALTS", "INFORM", "REQUEST", "GOODBYE",
             "THANK_YOU", "SELECT", "AFFIRM", "NEGATE")
SYSTEM_ACTS = ("INFORM", "REQUEST", "CONFIRM", "OFFER", "INFORM_COUNT", "OFFER_INTENT", "NOTIFY_SUCCESS",
               "NOTIFY_FAILURE", "REQ_MORE", "GOODBYE")
PREAMBLE = "user = USER()\nsystem = SYSTEM(user)\n"


@dataclass
class Service:
    name: str
    intents: list[str]
    slots: list[str]


@dataclass
class Converted:
    service: Service
    spec: str
    demonstrations: dict[str, str] = field(default_factory=dict)
    """dialogue_id → program, in the order read."""
    skipped: int = 0
    """Dialogues that involve another service too (or only other services)."""


def read_schema(path: Path, service: str | None) -> Service:
    services = expect(load_json(path), list, path, "")
    found: dict[str, Service] = {}
    for index, raw in enumerate(services):
        where = f"[{index}]"
        expect(raw, dict, path, where)
        name = key(raw, "service_name", str, path, where)
        intents = key(raw, "intents", list, path, where)
        intent_names = [python_name(key(expect(i, dict, path, f"{where}.intents[{n}]"), "name", str, path,
                                        f"{where}.intents[{n}]")) for n, i in enumerate(intents)]
        slots = [key(expect(s, dict, path, f"{where}.slots[{n}]"), "name", str, path, f"{where}.slots[{n}]")
                 for n, s in enumerate(key(raw, "slots", list, path, where))]
        for n, intent in enumerate(intent_names):
            if not intent.isidentifier() or keyword.iskeyword(intent) or intent in (*SYSTEM_ACTS, "set_query_status"):
                raise ConvertError(f"{path}: {where}.intents[{n}].name: {intent!r} cannot be a method of SYSTEM")
        found[name] = Service(name, intent_names, slots)
    if service is None:
        if len(found) != 1:
            raise ConvertError(f"{path}: lists {len(found)} services; choose one with --service "
                               f"({', '.join(sorted(found)[:10])}{', ...' if len(found) > 10 else ''})")
        return next(iter(found.values()))
    if service not in found:
        raise ConvertError(f"{path}: no service {service!r} (it lists {', '.join(sorted(found)[:10])})")
    return found[service]


def spec_program(service: Service) -> str:
    lines = [USER_SPEC, "class SYSTEM:", "  def __init__(self, user):", "    self.user = user",
             "    self.query_success = None"]
    for act in SYSTEM_ACTS:
        parameter = ", slot" if act in SLOT_ACTS else ", intent" if act in INTENT_ACTS else ""
        lines.append(f"  def {act}(self{parameter}): pass")
    lines += [f"  def {intent}(self): pass" for intent in service.intents]
    lines.append("  def set_query_status(self, status): self.query_success = status")
    return "\n".join(lines) + "\n"


def _act(actor: str, action: dict[str, Any], path: Path, where: str, acts: tuple[str, ...]) -> str:
    act = key(action, "act", str, path, where)
    if act not in acts:
        raise ConvertError(f"{path}: {where}.act: {act!r} is not a {actor} act of SGD ({', '.join(acts)})")
    if act in SLOT_ACTS:
        return f"{actor}.{act}({key(action, 'slot', str, path, where)!r})"
    if act in INTENT_ACTS:
        values = key(action, "values", list, path, where)
        if not values:
            raise ConvertError(f"{path}: {where}.values: {act} needs the intent as its first value")
        return f"{actor}.{act}({expect(values[0], str, path, f'{where}.values[0]')!r})"
    return f"{actor}.{act}()"


def dialogue_program(dialogue: dict[str, Any], service: Service, path: Path, where: str) -> str:
    lines = [PREAMBLE.rstrip("\n")]
    for t, turn in enumerate(key(dialogue, "turns", list, path, where)):
        turn_at = f"{where}.turns[{t}]"
        expect(turn, dict, path, turn_at)
        speaker = key(turn, "speaker", str, path, turn_at)
        if speaker not in ("USER", "SYSTEM"):
            raise ConvertError(f"{path}: {turn_at}.speaker: {speaker!r} (expected 'USER' or 'SYSTEM')")
        for f, frame in enumerate(key(turn, "frames", list, path, turn_at)):
            frame_at = f"{turn_at}.frames[{f}]"
            expect(frame, dict, path, frame_at)
            if key(frame, "service", str, path, frame_at) != service.name:
                continue
            if speaker == "SYSTEM" and "service_call" in frame:
                call = key(frame, "service_call", dict, path, frame_at)
                method = python_name(key(call, "method", str, path, f"{frame_at}.service_call"))
                if method not in service.intents:
                    raise ConvertError(f"{path}: {frame_at}.service_call.method: {method!r} is not an intent of "
                                       f"{service.name} ({', '.join(service.intents)})")
                results = key(frame, "service_results", list, path, frame_at)
                lines += [f"system.{method}()", f"system.set_query_status({bool(results)})"]
            actor, acts = ("user", USER_ACTS) if speaker == "USER" else ("system", SYSTEM_ACTS)
            for a, action in enumerate(key(frame, "actions", list, path, frame_at)):
                action_at = f"{frame_at}.actions[{a}]"
                lines.append(_act(actor, expect(action, dict, path, action_at), path, action_at, acts))
    return "\n".join(lines) + "\n"


def convert(schema: Path, dialogue_files: list[Path], service_name: str | None) -> Converted:
    service = read_schema(schema, service_name)
    converted = Converted(service, spec_program(service))
    for path in dialogue_files:
        for index, dialogue in enumerate(expect(load_json(path), list, path, "")):
            where = f"[{index}]"
            expect(dialogue, dict, path, where)
            dialogue_id = key(dialogue, "dialogue_id", str, path, where)
            services = key(dialogue, "services", list, path, where)
            if services != [service.name]:
                converted.skipped += 1
                continue
            converted.demonstrations[dialogue_id] = dialogue_program(dialogue, service, path, where)
    if not converted.demonstrations:
        raise ConvertError(f"no dialogue of {service.name} alone in {', '.join(str(p) for p in dialogue_files)} "
                           f"({converted.skipped} involve other services)")
    return converted
