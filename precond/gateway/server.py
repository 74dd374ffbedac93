"""How the gateway's HTTP server is started: one set of uvicorn options for the supervisor, the test stack,
the benchmarks and docker-compose (a test checks that compose says the same).

The HTTP implementation is httptools' (llhttp, in C), with the bound on a request head that h11 had and
httptools lacks (`service.http_protocol`): h11 parsed in Python, about an eighth of the gateway's CPU per check.

Several gateway processes may share the port (`PRECOND_GATEWAY_PROCESSES`, uvicorn's `--workers`): one event
loop is one core, and a cache hit is all gateway work.

The event loop is uvloop's (libuv): the same asyncio API with cheaper socket I/O and scheduling, which is what
the gateway spends its time on between requests (a flood of refused requests from one tenant delays the
others' `/health` and checks by the loop's per-request cost).
"""

GATEWAY_ARGS = (
    "precond.gateway.app:create_app",
    "--factory",
    "--loop",
    "uvloop",
    "--http",
    "precond.gateway.http_protocol:GatewayHttpProtocol",
)


def gateway_args(processes: int = 1) -> tuple[str, ...]:
    """The options above, with `processes` gateway processes sharing the port."""
    return GATEWAY_ARGS if processes <= 1 else (*GATEWAY_ARGS, "--workers", str(processes))
