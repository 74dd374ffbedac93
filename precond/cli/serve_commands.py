"""`precond serve` and `precond worker`: the service's processes, configured by flags over the environment."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import Annotated

import typer

from precond.gateway.settings import GatewaySettings, get_gateway_settings
from precond.worker.settings import WorkerSettings, get_worker_settings


def serve(
    port: Annotated[int | None, typer.Option(help="Gateway port [PORT, default 8000].")] = None,
    host: Annotated[str, typer.Option(help="Gateway bind address.")] = "127.0.0.1",
    workers: Annotated[int, typer.Option(min=1, help="Worker processes (each reads every queue).")] = 1,
    data_dir: Annotated[
        Path, typer.Option(help="Data dir of the private queue redis-server, if one is started.")
    ] = Path("var/redis"),
    no_auth: Annotated[
        bool, typer.Option("--no-auth", help="Serve without API keys on a non-loopback address (anyone may call).")
    ] = False,
    redis_maxmemory: Annotated[
        str, typer.Option(help="maxmemory of the private queue Redis (noeviction: full means 503, never loss).")
    ] = "512mb",
    cache_maxmemory: Annotated[
        str, typer.Option(help="maxmemory of the private cache Redis (allkeys-lru: evicts old results).")
    ] = "256mb",
    redis_url: Annotated[
        str | None,
        typer.Option(help="Use this Redis (sets REDIS_URL for every process), even one without a password; "
                     "default: REDIS_URL, else two private ones started here.", show_default=False),
    ] = None,
    redis_port: Annotated[
        int | None,
        typer.Option(min=1, max=65534, help="Port of the private queue Redis (the cache Redis takes the next one); "
                     "default: two free ports. A port something else holds is refused.", show_default=False),
    ] = None,
    no_rate_limit: Annotated[
        bool, typer.Option("--no-rate-limit", help="Local use without API keys: the one open tenant (`public`) "
                           "may send requests at any rate (PRECOND_PUBLIC_RATE_LIMIT=false); loopback only.")
    ] = False,
) -> None:
    """Run gateway, workers and, when REDIS_URL is unset, two private redis-servers (on two free ports, or
    --redis-port and the next; 127.0.0.1 only, with a random password per start, whatever else runs on the
    machine); says at start which Redis it uses, and again in the ready line.

    Without API keys (PRECOND_API_KEYS_FILE) the API is open: allowed on a loopback address, refused on any
    other unless --no-auth says so. Every caller is then the tenant `public`, held to the tenants' request rate
    unless --no-rate-limit (local use: a loopback address); the ready line says which.
    """
    from precond.cli.supervisor import Supervisor

    settings = get_gateway_settings()
    env = _lifted(settings, host) if no_rate_limit else {}
    _open_or_refused(settings, host, no_auth)
    port = settings.port if port is None else port
    worker_settings = _worker_settings(redis_url, redis_port)
    try:
        supervisor = Supervisor(
            worker_settings, host, port, workers, data_dir, gateway_processes=settings.processes,
            redis_maxmemory=redis_maxmemory, cache_maxmemory=cache_maxmemory, redis_port=redis_port,
            ready_note=open_tenant_note(settings, lifted=bool(env)), env=env,
        )
    except SystemExit as refused:  # what the user asked for cannot be served: said, not a traceback
        typer.echo(f"error: {refused.code}", err=True)
        raise typer.Exit(2) from None
    raise typer.Exit(supervisor.run())


def _open_or_refused(settings: GatewaySettings, host: str, no_auth: bool) -> None:
    """Without API keys: exit 2 on an address others reach unless --no-auth, else say the API is open."""
    if settings.api_keys_file is not None:
        return
    if not _loopback(host) and not no_auth:
        typer.echo(f"error: refusing to serve on {host} without API keys: anyone who can reach it could use it. "
                   "Make a key (precond keys create --tenant NAME --file keys.jsonl) and set "
                   "PRECOND_API_KEYS_FILE, or pass --no-auth.", err=True)
        raise typer.Exit(2)
    typer.echo(f"note: no API keys: the API on {host} is open to anyone who can reach it", err=True)


def _worker_settings(redis_url: str | None, redis_port: int | None) -> WorkerSettings:
    """The workers' settings with --redis-url; exit 2 for --redis-port beside a Redis that is not started here."""
    worker_settings = get_worker_settings()
    if redis_url is not None:
        worker_settings = worker_settings.model_copy(update={"redis_url": redis_url})
    if worker_settings.redis_url is not None and redis_port is not None:
        typer.echo("error: --redis-port is the port of the private Redis precond serve starts; with --redis-url "
                   "or REDIS_URL none is started", err=True)
        raise typer.Exit(2)
    return worker_settings


def _lifted(settings: GatewaySettings, host: str) -> dict[str, str]:
    """The setting --no-rate-limit gives every process, or exit 2 where it would lift a limit that protects
    someone: keyed tenants keep theirs, and an address others reach keeps the open tenant's."""
    if settings.api_keys_file is not None:
        typer.echo("error: --no-rate-limit lifts the rate of the open tenant of a service without API keys; with "
                   "PRECOND_API_KEYS_FILE every tenant keeps its rate (PRECOND_TENANT_RATE_PER_S)", err=True)
        raise typer.Exit(2)
    if not _loopback(host):
        typer.echo(f"error: --no-rate-limit is for local use (a loopback address), not --host {host}", err=True)
        raise typer.Exit(2)
    return {"PRECOND_PUBLIC_RATE_LIMIT": "false"}


def open_tenant_note(settings: GatewaySettings, lifted: bool) -> str:
    """What the ready line says a service without API keys lets its one tenant do (nothing with keys)."""
    if settings.api_keys_file is not None:
        return ""
    jobs = f"{settings.tenant_max_jobs} jobs at once"
    if lifted or not settings.public_rate_limit:
        return f"; no API keys: every caller is the tenant 'public', at any request rate, {jobs}"
    return (f"; no API keys: every caller is the tenant 'public', {settings.tenant_rate_per_s:g} requests/s "
            f"(bursts of {settings.tenant_burst}), {jobs} (--no-rate-limit lifts the rate)")


def _loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def worker(
    concurrency: Annotated[
        int | None, typer.Option(min=1, help="Model jobs at once [PRECOND_WORKER_CONCURRENCY].")
    ] = None,
    check_concurrency: Annotated[
        int | None, typer.Option(min=1, help="check-actions jobs at once [PRECOND_CHECK_CONCURRENCY].")
    ] = None,
    queues: Annotated[
        str | None, typer.Option(help="Comma list of the queues to read [PRECOND_WORKER_QUEUES, default all].",
                                 show_default=False),
    ] = None,
) -> None:
    """Run one worker process: loads the model (when it reads the model queue), heartbeats, runs the jobs of its
    queues from Redis."""
    from precond.worker.runner import run
    from precond.worker.settings import queue_names

    overrides: dict[str, object] = {"worker_concurrency": concurrency, "check_concurrency": check_concurrency}
    if queues is not None:
        try:
            overrides["worker_queues"] = ",".join(queue_names(queues))
        except ValueError as exc:
            typer.echo(f"error: --queues: {exc}", err=True)
            raise typer.Exit(2) from None
    settings = get_worker_settings().model_copy(update={k: v for k, v in overrides.items() if v is not None})
    run(settings)


def prepare_model() -> None:
    """Convert the configured model (`MODEL_*`) into MODEL_CACHE_DIR, with its int8 copy where MODEL_QUANT picks
    int8, and exit: a serving pod's init container runs it, so that the worker's memory limit holds the served
    model, not the one-time conversion (a full-width copy)."""
    from precond.engine.models.weights import serving_weights
    from precond.engine.settings import ModelSettings

    info = serving_weights(ModelSettings()).info
    typer.echo(f"{info.name} ready: {info.dtype}, quant {info.quant} ({info.quant_reason or info.dtype_reason})")


def sandbox_check() -> None:
    """Check that untrusted code can be confined here (as this user, with these capabilities, under this
    seccomp profile): prints what the sandbox's probe found; exit status 1 when it cannot, and a worker here
    would then refuse every job."""
    from precond.sandbox.selfcheck import main

    raise typer.Exit(main())


def register(app: typer.Typer) -> None:
    app.command()(serve)
    app.command()(worker)
    app.command("prepare-model")(prepare_model)
    app.command("sandbox-check")(sandbox_check)
