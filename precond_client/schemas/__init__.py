"""Request/response bodies shared by the CLI, the gateway and the worker (one place, one truth)."""
