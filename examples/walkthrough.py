"""The worked example of docs/writing-a-spec.md, end to end through the Python client:
spec → demonstrations → infer → vet → store and pin → check → re-infer with new demonstrations, as a dialog
system would call it (events, never code strings, for what the user said).

    python examples/walkthrough.py --server http://127.0.0.1:8000 --api-key pk_...   # a running service
    python examples/walkthrough.py                                                    # a throwaway local stack

Without --server it starts a local stack of its own (precond/stack/local.py: Redis, gateway, one worker; needs
redis-server and the full install). Every step checks what it got and exits non-zero when the answer is
not what the guide says (tests/client/test_walkthrough.py runs it, so the guide cannot rot).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout

from precond_client import Client, History, InferOptions, InferRequest, InvalidInput, JobStatus, rules

# 1. The spec: observations (USER's methods, with bodies that record what happened in its attributes) and
#    actions (SYSTEM's stubs, whose rules are unknown and will be inferred).
SPEC = """\
from collections import defaultdict

class USER:
    def __init__(self):
        self.informed_intent = defaultdict(lambda: False)
        self.informed_slot = defaultdict(lambda: False)
        self.requested_slot = defaultdict(lambda: False)
        self.affirmed = False
        self.no_more = False
    def INFORM_INTENT(self, intent): self.informed_intent[intent] = True
    def INFORM(self, slot): self.informed_slot[slot] = True
    def REQUEST(self, slot): self.requested_slot[slot] = True
    def AFFIRM(self): self.affirmed = True
    def GOODBYE(self): self.no_more = True

class SYSTEM:
    def __init__(self, user):
        self.user = user
        self.query_success = None
    def REQUEST(self, slot): pass
    def INFORM(self, slot): pass
    def OFFER(self, slot): pass
    def CONFIRM(self, slot): pass
    def FindBooks(self): pass
    def BorrowBook(self): pass
    def NOTIFY_SUCCESS(self): pass
    def GOODBYE(self): pass
    def set_query_status(self, status): self.query_success = status
"""

# 2. Demonstrations: dialogues that went right, as programs over the spec (`precond convert` writes these
#    from SGD files or JSON event logs).
START = "user = USER()\nsystem = SYSTEM(user)\n"
DEMONSTRATIONS = [
    START + """\
user.INFORM_INTENT('FindBooks')
system.REQUEST('author')
user.INFORM('author')
system.FindBooks()
system.set_query_status(True)
system.OFFER('title')
user.REQUEST('branch')
system.INFORM('branch')
user.INFORM_INTENT('BorrowBook')
system.CONFIRM('title')
user.AFFIRM()
system.BorrowBook()
system.set_query_status(True)
system.NOTIFY_SUCCESS()
user.GOODBYE()
system.GOODBYE()
""",
    START + """\
user.INFORM_INTENT('FindBooks')
user.INFORM('author')
system.FindBooks()
system.set_query_status(True)
system.OFFER('title')
user.INFORM_INTENT('BorrowBook')
system.CONFIRM('title')
user.AFFIRM()
system.BorrowBook()
system.set_query_status(True)
system.NOTIFY_SUCCESS()
user.GOODBYE()
system.GOODBYE()
""",
    START + """\
user.INFORM('author')
user.INFORM_INTENT('FindBooks')
system.FindBooks()
system.set_query_status(True)
system.OFFER('title')
user.REQUEST('due_date')
system.INFORM('due_date')
user.GOODBYE()
system.GOODBYE()
""",
]


def expect(condition: bool, what: str) -> None:
    if not condition:
        print(f"walkthrough: NOT AS THE GUIDE SAYS: {what}", file=sys.stderr)
        raise SystemExit(1)


def walkthrough(client: Client) -> None:
    # 3. Infer. `generators: ["enumerate"]` is the model-free path (about a second); the default adds the
    #    code model's candidates. Three dialogues are too thin for the default evidence-weighted validation
    #    (BorrowBook occurs twice: it would learn nothing), so `tolerance=0` asks for the paper's strict
    #    validation, which learns from every occurrence: read the rules (step 4) before they guard anything.
    #    A 202 is followed to the end; `progress` sees each status.
    def progress(status: JobStatus) -> None:
        print(f"  job {status.id[:16]}...: {status.status} {status.progress.phase} "
              f"{status.progress.done}/{status.progress.total}", file=sys.stderr)

    inferred = client.infer_preconditions(
        InferRequest(spec=SPEC, demonstrations=DEMONSTRATIONS,
                     options=InferOptions(generators=["enumerate"], tolerance=0)),
        progress=progress,
    )
    print("inferred rules:")
    for action, found in inferred.preconditions.items():
        print(f"  {action}: {found}")
    for action, warning in inferred.warnings.items():
        print(f"  warning {action}: {warning}")
    expect("self.user.informed_slot['author']" in inferred.preconditions["SYSTEM.FindBooks"],
           "FindBooks needs the author")
    expect("self.user.affirmed" in inferred.preconditions["SYSTEM.BorrowBook"], "BorrowBook needs a yes")
    expect("self.user.no_more" in inferred.preconditions["SYSTEM.GOODBYE"], "GOODBYE waits for the user")

    # 4. Vet: the rules are yours to read, keep, edit or drop before they guard anything. Here: keep every
    #    rule of the actions the system must never get wrong, and nothing for the rest.
    guarded = ["SYSTEM.FindBooks", "SYSTEM.BorrowBook", "SYSTEM.GOODBYE", "SYSTEM.INFORM"]
    vetted = {action: inferred.preconditions[action] for action in guarded}
    print("vetted rules:", vetted)

    # 5. Store and pin: the vetted rules become version 1 of a stored set (checked against the demonstrations
    #    on the server); the safety rule of BorrowBook is marked required, so no re-inference ever drops it.
    stored = client.create_set({"spec": SPEC, "preconditions": vetted, "demonstrations": DEMONSTRATIONS})
    pinned = client.edit_set(stored.id, [rules.require("SYSTEM.BorrowBook", "self.user.affirmed")],
                             base_version=stored.version)
    print(f"stored {stored.reference}, pinned {pinned.reference}: required {pinned.required}")
    expect(pinned.validation is not None and not pinned.validation.blocked, "the vetted rules allow every demo")

    # 6. Check, from the dialog system: before it acts, it asks whether its candidate calls are allowed after
    #    the dialogue so far, naming the set and sending the dialogue as events (what the user typed is only
    #    ever an argument: a literal, never code). No model, answered in milliseconds on its own queue.
    history = History().user("INFORM_INTENT", "FindBooks").user("REQUEST", "branch")
    calls = ["system.FindBooks()", "system.REQUEST('author')", "system.INFORM('branch')", "system.GOODBYE()"]
    verdicts = client.check_with_set(pinned.reference, history, calls)
    allowed = {v.call: v.allowed for v in verdicts.results}
    for verdict in verdicts.results:
        print(f"  {verdict.call}: {'allowed' if verdict.allowed else 'refused ' + str(verdict.violations)}")
    expect(not allowed["system.FindBooks()"], "FindBooks before the author is refused")
    expect(allowed["system.REQUEST('author')"], "asking for the author is allowed")
    expect(allowed["system.INFORM('branch')"], "answering the user's question is allowed")
    expect(not allowed["system.GOODBYE()"], "GOODBYE before the user is done is refused")
    odd = History().user("INFORM_INTENT", "FindBooks").user("REQUEST", "branch'); import os; ('")
    expect(client.check_with_set(pinned.reference, odd, ["system.GOODBYE()"]).results[0].error is None,
           "a quote in what the user said is data, not code")

    # 7. Re-infer with new demonstrations: the new version keeps the required rule, and its `diff` says what
    #    was added, removed (and why), kept. A demonstration that breaks a required rule is refused.
    # A user who asks to borrow a book by an author: the system searches without a FindBooks intent, so
    # "FindBooks needs the FindBooks intent" no longer holds and goes, with the reason in the diff.
    new = START + """\
user.INFORM_INTENT('BorrowBook')
user.INFORM('author')
system.FindBooks()
system.set_query_status(True)
system.OFFER('title')
system.CONFIRM('title')
user.AFFIRM()
system.BorrowBook()
system.set_query_status(True)
system.NOTIFY_SUCCESS()
user.GOODBYE()
system.GOODBYE()
"""
    redone = client.reinfer_set(pinned.id, [new], actions=guarded, options=InferOptions(generators=["enumerate"]),
                                base_version=pinned.version, progress=progress)
    diff = redone.diff
    expect(diff is not None, "a re-inferred version carries its diff")
    assert diff is not None
    print(f"re-inferred {redone.reference} from version {diff.base_version} with {diff.new_demonstrations} new "
          "demonstration(s):")
    for part in ("added", "removed", "kept", "required_kept"):
        for change in getattr(diff, part):
            print(f"  {part}: {change.action}: {change.rule}  ({change.reason})")
    expect("self.user.affirmed" in redone.preconditions["SYSTEM.BorrowBook"], "the required rule is kept")
    gone = {(c.action, c.rule): c.reason or "" for c in diff.removed}
    expect("violated at" in gone.get(("SYSTEM.FindBooks", "self.user.informed_intent['FindBooks']"), ""),
           "the rule the new demonstration refutes is removed, saying where")
    expect(len(redone.demonstrations) == len(DEMONSTRATIONS) + 1, "the new version stores every demonstration")
    rash = START + "user.INFORM_INTENT('BorrowBook')\nsystem.BorrowBook()\n"
    try:
        client.reinfer_set(pinned.id, [rash], actions=guarded, options=InferOptions(generators=["enumerate"]))
    except InvalidInput as refused:
        print(f"refused: {refused.field}: {refused.message}")
        expect(refused.type == "blocks_demonstration" and refused.field == "demonstrations[0]",
               "a demonstration that breaks a required rule is refused, naming it")
    else:
        expect(False, "a demonstration that breaks a required rule is refused")
    print("walkthrough: ok")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", help="URL of a running service (default: start a local stack)")
    parser.add_argument("--api-key", default=os.environ.get("PRECOND_API_KEY"), help="or PRECOND_API_KEY")
    args = parser.parse_args()
    if args.server:
        with Client(args.server, api_key=args.api_key) as client:
            walkthrough(client)
        return
    from precond.stack.local import make_stack, serving
    from precond.stack.tiny_model import build_tiny_model

    with tempfile.TemporaryDirectory() as tmp:
        model = build_tiny_model(Path(tmp) / "model")  # the steps here are model-free: a tiny model suffices
        with serving(make_stack(Path(tmp), model), workers=1) as stack, Client(stack.base_url) as client:
            walkthrough(client)


if __name__ == "__main__":
    main()
