"""The paper's pipeline: spec reading, prompting, candidate parsing, enumeration, ranking, Algorithm 1, and the
code-model backend (`engine.models`). It knows nothing of queues or HTTP: the CLI calls it in-process, the
queue worker (`precond/worker/`) calls it per job.

Kept import-free on purpose: `engine.settings` must be importable without torch.
"""
