"""Attacks on the sandbox boundary from code that first switches off every Python-level guard.

Run by test_boundary.py in-process and, as a separate program, under another (non-root) uid: it prints
one JSON object, attack name -> outcome ("denied: ..." or "ALLOWED: ..."). Kept as a plain script so the
same attacks run unchanged in both deployments.
"""

from __future__ import annotations

import json
import os
import sys

from sandbox import Limits, Sandbox

SPEC = "class A:\n    def __init__(self):\n        self.x = 1\n    def act(self, v):\n        pass\n"
CANARY = "/tmp/sandbox_boundary_canary"

# No dunder literal anywhere: the guards that read source text never see one. The first lines take the
# real builtins, `sys`, `os` and `ctypes` back, so nothing but the kernel stands in the way.
ATTACK = '''
def find(name):
    base = getattr(getattr((), '__cl' + 'ass__'), '__ba' + 'se__')
    for c in getattr(base, '__subcl' + 'asses__')():
        g = getattr(getattr(c, '__in' + 'it__'), '__glo' + 'bals__', None)
        if isinstance(g, dict) and name in g:
            return g[name]
    raise LookupError(name)
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
'''.replace('CANARY', repr(CANARY))


def run_attacks(sandbox: Sandbox) -> dict[str, str]:
    if os.path.exists(CANARY):
        os.unlink(CANARY)
    trace = sandbox.trace(SPEC, [ATTACK])
    (values,) = trace.actions["A.act"].arg_values
    outcome: dict[str, str] = eval(str(values[0]), {"__builtins__": {}})  # a dict literal of strings
    outcome["canary file exists"] = "ALLOWED" if os.path.exists(CANARY) else "denied"
    return outcome


if __name__ == "__main__":
    with Sandbox(Limits(timeout_s=20, cpu_s=10), workers=1) as box:
        print(json.dumps({"uid": os.getuid(), "results": run_attacks(box)}))
    sys.exit(0)
