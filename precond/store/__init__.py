"""Every versioned thing a tenant keeps, one module per kind over the one tenant store.

`tenant_store` keeps records as numbered, never rewritten versions in the queue Redis, bounded per tenant and
written by one script; `sets` is precondition sets on it (a version's review summary, its bounds, its static check,
the union of demonstrations; the counterexamples a set keeps are part of its version); `reinference` is the version
a re-inference makes from its base and its store; `policies` is trained policies (LoRA adapters, their weights a
counted part of each version). The gateway (`precond/gateway/set_store.py` answers HTTP over `sets`) and the worker
import this package; it imports the job protocol (`precond.jobs`) for its key prefix and scripts, never them.
"""
