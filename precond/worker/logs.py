"""The worker's log: one process runs an arq worker per queue (three), and arq logs each one's start and stop
in the same words, so every such line came three times. `Deduplicated` keeps the first of identical lines
within a few seconds; a line that differs (another queue's job counts at shutdown, a job's own line) stays."""

from __future__ import annotations

import logging
import re
import time

REDIS_INFO = re.compile(r"^redis_version=")
NUMBER = re.compile(r"\d+(\.\d+)*[KMG]?")


class Deduplicated(logging.Filter):
    """Drops a record whose message repeats one logged less than `window_s` ago (the Redis information line
    compared without its numbers: memory use and client counts move between the three workers' calls)."""

    def __init__(self, window_s: float = 5.0) -> None:
        super().__init__()
        self.window_s = window_s
        self.last: dict[str, float] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        key = NUMBER.sub("#", message) if REDIS_INFO.match(message) else message
        now = time.monotonic()
        previous = self.last.get(key)
        self.last = {k: t for k, t in self.last.items() if now - t < self.window_s}  # bounded: recent lines only
        self.last[key] = now
        return previous is None or now - previous >= self.window_s


def configure() -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    logging.getLogger("arq.worker").addFilter(Deduplicated())
