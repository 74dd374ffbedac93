"""A real local stack for tests and benchmarks: redis-server, the uvicorn gateway and worker processes on free
loopback ports (`stack.local`), the tiny random code model they load (`stack.tiny_model`), and the reliability
scenarios run against them (`stack.harness`, `stack.scenarios`, `stack.hostile`).

tests/ and bench/ both import it; it imports nothing from either.
"""
