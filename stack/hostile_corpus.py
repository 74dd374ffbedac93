"""The hostile corpus: programs, assertions and calls that try to leave the sandbox or exhaust it.

Shared by the sandbox tests (tests/sandbox/test_hostile.py, each program in every role) and the API-level
hostile requests (stack/hostile.py, tests/reliability and bench/reliability.py). Paths the programs try to
write are `OUTSIDE`; callers substitute canary paths of their own.
"""

from __future__ import annotations

from pathlib import Path

# Reaches real modules through introspection without a literal dunder, to exercise the layers behind
# the AST filter and the restricted builtins: what stands in its way then is the kernel.
FIND = '''
def find(name):
    base = getattr(getattr((), '__cl' + 'ass__'), '__ba' + 'se__')
    for c in getattr(base, '__subcl' + 'asses__')():
        g = getattr(getattr(c, '__in' + 'it__'), '__glo' + 'bals__', None)
        if isinstance(g, dict) and name in g:
            return g[name]
    raise LookupError(name)
'''

OUTSIDE = Path("/tmp/sandbox_test_pwned")
PASSWD_MARK = "root:x:0:0"

PROGRAMS = {
    "loop": "while True:\n    pass\n",
    "fork_bomb_import": "import os\nwhile True:\n    os.fork()\n",
    "fork_bomb_walk": "while True:\n    ().__class__.__base__.__subclasses__()\n",
    "fork_bomb_getattr": FIND + "while True:\n    find('fork')()\n",
    "allocate_10gb": "x = bytearray(10 * 1024 ** 3)\n",
    "recursion": "def f():\n    return f()\nf()\n",
    "write_outside": f"open({str(OUTSIDE)!r}, 'w').write('x')\n",
    "write_outside_getattr": FIND + f"find('open')({str(OUTSIDE)!r}, 'w').write('x')\n",
    "read_passwd": "raise ValueError(open('/etc/passwd').read())\n",
    "read_passwd_getattr": FIND + "raise ValueError(find('open')('/etc/passwd').read())\n",
    "socket": "import socket\nsocket.create_connection(('127.0.0.1', 22))\n",
    "os_system": "import os\nos.system('touch /tmp/sandbox_test_pwned')\n",
    "os_system_getattr": FIND + f"find('system')('touch {OUTSIDE}')\n",
    "subclasses": "x = [c for c in ().__class__.__base__.__subclasses__()]\n",
    "dunder_import": "__import__('os').system('true')\n",
    "sys_exit": "import sys\nsys.exit(3)\n",
    "system_exit": "raise SystemExit(3)\n",
    "kill_parent": FIND + "find('kill')(find('getppid')(), 9)\n",
    "output_100mb": "print('x' * 100_000_000)\n",
    "non_utf8_output": "print('\\udcff\\udc80')\nraise ValueError('\\udcff bad \\x00')\n",
    "str_raises": "class E(Exception):\n    def __str__(self):\n        raise ValueError()\nraise E()\n",
    "str_loops": ("class E(Exception):\n    def __str__(self):\n        while True:\n            pass\n"
                  "raise E()\n"),
}

CANDIDATES = {
    "loop": "any(iter(int, 1))",
    "allocate_10gb": "len([0] * (10 * 1024 ** 3))",
    "recursion": "(lambda f: f(f))(lambda f: f(f))",
    "read_passwd": "open('/etc/passwd').read()",
    "subclasses": "().__class__.__base__.__subclasses__()",
    "dunder_import": "__import__('os').system('true')",
    "getattr": "getattr(self, 'x')",
    "output_100mb": "print('x' * 100_000_000)",
    "statement": "x = 1",
    "two_expressions": "self.x; self.x",
    "non_utf8": "'\\udcff' == v",
}

CALLS = [
    "a.act(__import__('os'))", "os.system('true')", "a.act(open('/etc/passwd').read())",
    "a.__class__.__base__()", "a.act(1); a.act(2)", "a.act(*[1])", "a.act(1)\nimport os",
    "while True: pass", "a.act('\\udcff')",
]

# Programs the kernel refuses without an exception: the call returns an error code (os.system → -1) and the
# program goes on, so the answer may be an ordinary 200; what matters is that nothing was done.
REFUSED_QUIETLY = frozenset({"os_system_getattr"})
