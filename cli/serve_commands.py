"""`precond serve` and `precond worker`: the service's processes, configured by flags over the environment."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from jobs.settings import get_gateway_settings, get_worker_settings


def serve(
    port: Annotated[int | None, typer.Option(help="Gateway port [PORT, default 8000].")] = None,
    host: Annotated[str, typer.Option(help="Gateway bind address.")] = "127.0.0.1",
    workers: Annotated[int, typer.Option(min=1, help="Worker processes (each serves both queues).")] = 1,
    data_dir: Annotated[
        Path, typer.Option(help="Data dir of the private redis-server, if one is started.")
    ] = Path("var/redis"),
) -> None:
    """Run gateway, workers and, when REDIS_URL is unset and none answers locally, a redis-server."""
    from service.supervisor import Supervisor

    port = get_gateway_settings().port if port is None else port
    raise typer.Exit(Supervisor(get_worker_settings(), host, port, workers, data_dir).run())


def worker(
    concurrency: Annotated[
        int | None, typer.Option(min=1, help="Model jobs at once [PRECOND_WORKER_CONCURRENCY].")
    ] = None,
    check_concurrency: Annotated[
        int | None, typer.Option(min=1, help="check-actions jobs at once [PRECOND_CHECK_CONCURRENCY].")
    ] = None,
) -> None:
    """Run one worker process: loads the model, heartbeats, runs model and check jobs from Redis."""
    from worker.runner import run

    overrides = {"worker_concurrency": concurrency, "check_concurrency": check_concurrency}
    settings = get_worker_settings().model_copy(update={k: v for k, v in overrides.items() if v is not None})
    run(settings)


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command()(worker)
