"""Static reading of trajectory programs (specs, demonstrations, histories), stdlib only.

One definition of what an action, an observation and a stub are, shared by the engine, the enumerator,
the evaluation and the sandbox child (which imports it under ``python -I -S``, so it must stay stdlib-only
and must never execute what it reads).
"""

from precond.programs.purity import Purity
from precond.programs.spec import Method, is_stub, main_body, read_methods

__all__ = ["Method", "Purity", "is_stub", "main_body", "read_methods"]
