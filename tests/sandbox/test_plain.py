"""Which assertions may share a sandbox child: the worker-side test that keeps tampering candidates apart."""

from __future__ import annotations

import pytest

from precond.sandbox.plain import is_plain, vocabulary

SPEC = '''import typing
from collections import defaultdict
REQUIRED = ("city", "date")
def known(slots, slot):
    return slots[slot]
class USER:
    def __init__(self):
        self.informed_slot = defaultdict(bool)
        self.no_more = False
class SYSTEM:
    def __init__(self, user):
        self.user = user
        self.query_success = None
    def REQUEST(self, slot):
        pass
'''


@pytest.mark.parametrize("expression", [
    "self.user.informed_slot[slot]", "not self.query_success", "slot in REQUIRED",
    "known(self.user.informed_slot, slot)",
    "self.user.informed_slot.get(slot, False)", "len([s for s in REQUIRED if self.user.informed_slot[s]]) == 2",
    "isinstance(self.user, USER) and (self.query_success is None or self.user.no_more)", "f'{slot}' != ''",
    "undefined_name == 1",  # can only raise NameError
])
def test_ordinary_rules_are_plain(expression: str) -> None:
    assert is_plain(expression, ("slot",), vocabulary(SPEC))


@pytest.mark.parametrize("expression", [
    "typing.sys.modules['builtins']",  # an imported module
    "defaultdict is None",  # imported names too
    "[g.gi_frame.f_back for g in [(x for x in ())]]",  # frames
    "self.user.__class__",  # dunders
    "'{0.user}'.format(self)",  # format reads attributes by name
    "getattr(self, 'user')", "vars(self)", "type(self)",  # builtins outside the fixed set
    "(lambda: self)()", "[f() for f in [len]]",  # calling what a comprehension or lambda binds
    "self.user.mro", "not a single expression (",
])
def test_anything_else_is_judged_alone(expression: str) -> None:
    assert not is_plain(expression, ("slot",), vocabulary(SPEC))
