"""The hostile corpus: programs, assertions and calls that try to leave the sandbox or exhaust it.

Shared by the sandbox tests (tests/sandbox/test_hostile.py, each program in every role) and the API-level
hostile requests (precond/stack/hostile.py, tests/reliability and bench/reliability.py). Paths the programs try to
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

# Switches off every Python-level guard in the sandbox child: takes the real builtins, `sys`, `os`,
# `ctypes` and `resource` back (no dunder literal anywhere, so text filters never see one), and empties
# the audit-hook tables older children kept in `__main__`. What still stands in the way is the kernel.
GUARDS_OFF = FIND + '''
B = find('builtins')
real_import = getattr(B, '__imp' + 'ort__')
sys = real_import('sys')
sys.stdout = getattr(sys, '__std' + 'out__')
main = sys.modules.get('__main__')  # older children kept their audit-hook tables here: empty them
for table, empty in (('_BLOCKED_EVENTS', frozenset()), ('_BLOCKED_PREFIXES', ()), ('_PATH_EVENTS', {})):
    if hasattr(main, table):
        getattr(B, 'setattr')(main, table, empty)
getattr(B, 'setattr')(B, 'open', getattr(B, 'open'))
os = real_import('os')
ctypes = sys.modules['ctypes']
resource = sys.modules['resource']
libc = ctypes.CDLL(None, use_errno=True)
'''

# After GUARDS_OFF: files, /proc, environment, network, signals, processes, limits. Each attempt records
# "denied: ..." or "ALLOWED: ..." in `results`; CANARY is a path the caller substitutes.
ATTACKS = '''
results = {}
def attempt(name, fn):
    try:
        value = fn()
        if isinstance(value, int) and value < 0:
            results[name] = 'denied: returned ' + str(value)
        else:
            results[name] = 'ALLOWED: ' + repr(value)[:200]
    except BaseException as e:
        results[name] = 'denied: ' + getattr(type(e), '__na' + 'me__') + ' ' + str(e)[:80]
attempt('read /etc/passwd', lambda: getattr(B, 'open')('/etc/passwd').read())
attempt('write a file', lambda: getattr(B, 'open')(CANARY, 'w').write('x'))
attempt('list /', lambda: os.listdir('/'))
attempt('read own environ', lambda: getattr(B, 'open')('/proc/self/environ').read())
attempt('environment', lambda: dict(os.environ) or -1)
attempt('parent pipes via /proc', lambda: os.open('/proc/%d/fd/1' % os.getppid(), os.O_WRONLY))
attempt('socket', lambda: libc.socket(2, 1, 0))
attempt('kill the fork server', lambda: os.kill(os.getppid(), 0))
attempt('kill pid 1', lambda: os.kill(1, 0))
attempt('pidfd_open', lambda: os.pidfd_open(os.getppid()))
attempt('tgkill syscall', lambda: libc.syscall(234, os.getppid(), os.getppid(), 0))
attempt('fork', lambda: os.fork())
attempt('execve', lambda: os.execv('/bin/sh', ['sh', '-c', 'true']))
attempt('ptrace', lambda: libc.ptrace(16, os.getppid(), 0, 0))
attempt('process_vm_readv', lambda: libc.syscall(310, os.getppid(), 0, 0, 0, 0, 0))
attempt('prlimit the fork server', lambda: resource.prlimit(os.getppid(), resource.RLIMIT_NPROC, (0, 0)))
attempt('raise own cpu limit', lambda: resource.setrlimit(resource.RLIMIT_CPU, (99, 99)))
attempt('prctl', lambda: libc.prctl(4, 1, 0, 0, 0))
attempt('unshare', lambda: libc.unshare(0x10000000))
attempt('memfd_create', lambda: os.memfd_create('x'))
a = A()
a.act(repr(results))
'''
