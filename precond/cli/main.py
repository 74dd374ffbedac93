"""The `precond` console script: one entry point, subcommands registered by the module that owns them."""

from __future__ import annotations

import typer

from precond.cli import (
    convert_commands,
    engine_commands,
    eval_commands,
    keys_commands,
    mcp_commands,
    serve_commands,
)

app = typer.Typer(
    help="Precondition reasoning as a service: infer verified preconditions, pick verified next actions.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
engine_commands.register(app)
serve_commands.register(app)
eval_commands.register(app)
keys_commands.register(app)
convert_commands.register(app)
mcp_commands.register(app)
