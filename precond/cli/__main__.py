"""`python -m precond.cli`: the same as the `precond` console script."""

from precond.cli.main import app

app()
