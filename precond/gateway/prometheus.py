"""Prometheus metrics of the gateway, plus the workers' counters that they keep in Redis.

Workers are many short-lived processes without a scrape port of their own, so they add their job outcomes,
phase durations and sandbox failures to one Redis hash; the gateway turns its latest read into metric
families at scrape time. Each app gets its own registry so several apps (tests) can live in one process.
"""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client.core import CounterMetricFamily, Metric, SummaryMetricFamily
from prometheus_client.registry import Collector

from precond.jobs.records import StatsSnapshot


class WorkerStats(Collector):
    """Holds the last snapshot of the workers' Redis hash; `collect` runs synchronously inside a scrape."""

    def __init__(self) -> None:
        self.snapshot = StatsSnapshot()

    def collect(self) -> Iterator[Metric]:
        jobs = CounterMetricFamily("precond_jobs", "Jobs finished by workers.", labels=["kind", "outcome"])
        phases = SummaryMetricFamily(
            "precond_job_phase_seconds", "Time jobs spent per engine phase.", labels=["kind", "phase"]
        )
        sandbox = CounterMetricFamily("precond_sandbox_failures", "Jobs stopped by a sandbox limit.")
        queued = SummaryMetricFamily(
            "precond_queue_seconds", "Time jobs waited in the queue before a worker started them, by tenant "
            "(its tag: the HMAC of its name, as in its job ids) and kind.", labels=["tenant", "kind"],
        )
        snapshot = self.snapshot
        for labels, seconds in sorted(snapshot.queue_sum.items()):
            queued.add_metric(list(labels), count_value=int(snapshot.queue_count.get(labels, 0.0)), sum_value=seconds)
        sandbox.add_metric([], snapshot.sandbox_failures)
        for labels, value in sorted(snapshot.jobs.items()):
            jobs.add_metric(list(labels), value)
        for labels, seconds in sorted(snapshot.phase_sum.items()):
            count = int(snapshot.phase_count.get(labels, 0.0))
            phases.add_metric(list(labels), count_value=count, sum_value=seconds)
        yield from (jobs, phases, sandbox, queued)


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter(
            "precond_http_requests", "HTTP requests by tenant tag (the HMAC of its name, as in its job ids; `-`: "
            "not authenticated).",
            ["route", "method", "status", "tenant"], registry=self.registry,
        )
        self.rejections = Counter(
            "precond_rejections", "Requests refused before any work, by tenant tag and reason "
            "(rate, jobs, queue, work).", ["tenant", "reason"], registry=self.registry,
        )
        self.latency = Histogram(
            "precond_http_request_seconds",
            "HTTP request latency, waiting for the job included; `judged_by`: what judged a check (`interpreter`: "
            "the gateway itself, `sandbox`: a worker; `-` for other routes).",
            ["route", "method", "judged_by"],
            buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60),
            registry=self.registry,
        )
        self.cache = Counter(
            "precond_cache", "Result cache lookups.", ["kind", "result"], registry=self.registry
        )
        self.queue_depth = Gauge(
            "precond_queue_depth", "Jobs waiting per queue.", ["queue"], registry=self.registry
        )
        self.workers = Gauge(
            "precond_workers", "Live workers (by heartbeat).", ["model_loaded"], registry=self.registry
        )
        self.worker_stats = WorkerStats()
        self.registry.register(self.worker_stats)
