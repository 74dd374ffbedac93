"""Names as Python reads them.

Python normalises every identifier to NFKC when it parses a program (PEP 3131): `def ｒｅｓｕｌｔ(self)`
defines `result`, and `ｓｅｌｆ` is `self`. A name that becomes code is therefore checked (reserved, a keyword,
listed twice, a method of the spec) in that form, never in the form it was sent in: otherwise a tool named
with fullwidth letters passes the check and then replaces the method whose name it spells.
"""

from __future__ import annotations

import unicodedata


def python_name(name: str) -> str:
    """The identifier Python binds for `name`."""
    return unicodedata.normalize("NFKC", name)
