"""How the gateway's HTTP server is started: one set of uvicorn options for the supervisor, the test stack,
the benchmarks and docker-compose (a test checks that compose says the same).

h11 rejects a request head that arrives over several reads once its buffer passes
`--h11-max-incomplete-event-size` (16 KiB by default) and answers with a plain-text 400, but parses the same
head when it arrives in one read; whether a 20-60 KiB URL got the app's JSON error therefore depended on
TCP segmentation. With a 128 KiB limit every head up to that size reaches the app, which answers with its own
JSON error, whatever the timing; a longer one may still get the server's plain-text 400. The HTTP
implementation is pinned to h11 so that this limit is the one in force (httptools has its own).

Several gateway processes may share the port (`PRECOND_GATEWAY_PROCESSES`, uvicorn's `--workers`): one event
loop is one core, and a cache hit is all gateway work.

The event loop is uvloop's (libuv): the same asyncio API with cheaper socket I/O and scheduling, which is what
the gateway spends its time on between requests (a flood of refused requests from one tenant delays the
others' `/health` and checks by the loop's per-request cost).
"""

MAX_REQUEST_HEAD_BYTES = 128 * 1024

GATEWAY_ARGS = (
    "service.app:create_app",
    "--factory",
    "--loop",
    "uvloop",
    "--http",
    "h11",
    "--h11-max-incomplete-event-size",
    str(MAX_REQUEST_HEAD_BYTES),
)


def gateway_args(processes: int = 1) -> tuple[str, ...]:
    """The options above, with `processes` gateway processes sharing the port."""
    return GATEWAY_ARGS if processes <= 1 else (*GATEWAY_ARGS, "--workers", str(processes))
