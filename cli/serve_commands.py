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
        Path, typer.Option(help="Data dir of the private queue redis-server, if one is started.")
    ] = Path("var/redis"),
    redis_maxmemory: Annotated[
        str, typer.Option(help="maxmemory of the private queue Redis (noeviction: full means 503, never loss).")
    ] = "512mb",
    cache_maxmemory: Annotated[
        str, typer.Option(help="maxmemory of the private cache Redis (allkeys-lru: evicts old results).")
    ] = "256mb",
) -> None:
    """Run gateway, workers and, when REDIS_URL is unset and none answers locally, two private redis-servers
    (queue on 6379, cache on 6380; 127.0.0.1 only, with a random password per start)."""
    from service.supervisor import Supervisor

    port = get_gateway_settings().port if port is None else port
    supervisor = Supervisor(
        get_worker_settings(), host, port, workers, data_dir,
        redis_maxmemory=redis_maxmemory, cache_maxmemory=cache_maxmemory,
    )
    raise typer.Exit(supervisor.run())


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
