"""The paper's pipeline, in rooms by what they do: `candidates` generates candidate rules (prompting, parsing the
model's samples, enumeration), `judging` judges them on the demonstrations (evidence, ranking, selection, the
report), `acting` acts on them (Algorithm 1's next action, behaviour cloning); `models` is the code-model backend.
At the top, the `Engine` (`engine.engine`) that runs an inference's stages, a check and a next action. It knows
nothing of queues or HTTP: the CLI calls it in-process, the queue worker (`precond/worker/`) calls it per job.

Kept import-free on purpose: `engine.settings` must be importable without torch.
"""
