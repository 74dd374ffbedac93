"""`python -m cli`: the same as the `precond` console script."""

from cli.main import app

app()
