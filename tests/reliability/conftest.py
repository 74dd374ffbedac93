"""Each reliability test builds its own stack (Redis, gateway, workers) in its own temp dir: they break things."""
