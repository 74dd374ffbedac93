"""Turn users' own dialog data into specs, demonstration programs and requests (docs/converting.md):
`sgd` reads the Schema-Guided Dialogue dataset's files, `events` generic JSON event logs. Standard library,
`precond/programs/`, `precond_client/schemas/` and `precond_client/openai_log.py` (what the embedded guard
shares) only."""
