"""Each replacement of a library's internals checks that what it replaces is there (precond/patches/): on the
versions pyproject.toml allows every one applies; on a library that lacks what one replaces or reads, it leaves the
library as it is and says so in the log."""

from __future__ import annotations

import logging
from typing import Any

import hiredis
import pytest
from redis.asyncio.connection import AbstractConnection, ConnectionPool
from starlette.requests import Request
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from precond.gateway import http_protocol, middleware
from precond.patches import redis_checkout, redis_packing, redis_sending


def test_on_the_allowed_versions_every_patch_applies() -> None:
    assert redis_packing.pack_with_hiredis()
    assert redis_sending.send_without_task()
    assert redis_checkout.check_out_without_read()
    assert http_protocol.GatewayHttpProtocol is http_protocol.BoundedHttpToolsProtocol
    middleware._hand_over_parsed.cache_clear()
    assert middleware._hand_over_parsed()


def off(caplog: pytest.LogCaptureFixture, lacking: str) -> None:
    """The one log line of a patch switched off, naming what it lacks."""
    lines = [r.getMessage() for r in caplog.records if r.name == "precond.patches"]
    assert len(lines) == 1 and ": off, this library version lacks " in lines[0] and lacking in lines[0], lines


def test_packing_stays_redis_py_s_where_hiredis_cannot_pack(monkeypatch: pytest.MonkeyPatch,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    before = AbstractConnection.pack_command
    monkeypatch.delattr(hiredis, "pack_command")
    with caplog.at_level(logging.WARNING, "precond.patches"):
        assert not redis_packing.pack_with_hiredis()
    assert AbstractConnection.pack_command is before
    off(caplog, "hiredis.pack_command")


def test_sending_stays_redis_py_s_where_a_connection_has_no_writer(monkeypatch: pytest.MonkeyPatch,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    def init_without_writer(self: Any, *args: Any, **kwargs: Any) -> None:
        self.health_check_interval = 0

    before = AbstractConnection.send_packed_command
    monkeypatch.setattr(AbstractConnection, "__init__", init_without_writer)
    with caplog.at_level(logging.WARNING, "precond.patches"):
        assert not redis_sending.send_without_task()
    assert AbstractConnection.send_packed_command is before
    off(caplog, "AbstractConnection()._writer")


def test_check_out_stays_redis_py_s_where_the_pool_checks_otherwise(monkeypatch: pytest.MonkeyPatch,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delattr(ConnectionPool, "ensure_connection")
    with caplog.at_level(logging.WARNING, "precond.patches"):
        assert not redis_checkout.check_out_without_read()
    assert not hasattr(ConnectionPool, "ensure_connection")  # nothing put in its place
    off(caplog, "ConnectionPool.ensure_connection")


def test_the_gateway_speaks_h11_where_uvicorn_s_httptools_protocol_changed(monkeypatch: pytest.MonkeyPatch,
                                                                          caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delattr(HttpToolsProtocol, "send_400_response")
    with caplog.at_level(logging.WARNING, "precond.patches"):
        assert http_protocol._chosen() is H11Protocol
    off(caplog, "HttpToolsProtocol.send_400_response")


def test_a_parsed_body_is_not_handed_over_where_starlette_keeps_it_elsewhere(monkeypatch: pytest.MonkeyPatch,
                                                                           caplog: pytest.LogCaptureFixture) -> None:
    async def json_kept_elsewhere(self: Any) -> Any:
        return self._parsed_body

    monkeypatch.setattr(Request, "json", json_kept_elsewhere)
    middleware._hand_over_parsed.cache_clear()
    with caplog.at_level(logging.WARNING, "precond.patches"):
        assert not middleware._hand_over_parsed()
    middleware._hand_over_parsed.cache_clear()
    off(caplog, "Request()._json")
