"""`precond keys create|list|revoke`: the API keys file the gateway reads (`PRECOND_API_KEYS_FILE`).

A key is shown once, when it is made; the file keeps only its SHA-256. The gateway notices every change of
the file at its next request, so neither a new key nor a revocation needs a restart.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Annotated

import typer

from precond.gateway.api_keys import KeyRecord, digest, new_key, read_records, write_records
from precond.gateway.settings import get_gateway_settings

keys = typer.Typer(help="Manage the gateway's API keys (hashed in PRECOND_API_KEYS_FILE).", no_args_is_help=True)

KeysFile = Annotated[Path | None, typer.Option("--file", help="The keys file [PRECOND_API_KEYS_FILE].")]


def _path(file: Path | None) -> Path:
    path = file or get_gateway_settings().api_keys_file
    if path is None:
        typer.echo("error: no keys file: pass --file or set PRECOND_API_KEYS_FILE", err=True)
        raise typer.Exit(2)
    return path


def _records(path: Path) -> list[KeyRecord]:
    if not path.exists():
        return []
    try:
        return read_records(path)
    except (OSError, ValueError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None


@keys.command()
def create(
    tenant: Annotated[str, typer.Option(help="Who the key belongs to: its jobs, cache and quotas are this tenant's.")],
    file: KeysFile = None,
    expires_days: Annotated[int | None, typer.Option(min=1, help="Days until the key stops working.")] = None,
    if_none: Annotated[bool, typer.Option(help="Only if the file holds no usable key yet (first start).")] = False,
    operator: Annotated[bool, typer.Option(
        help="The key also reads why the service is not ready (/ready, /health): an operator's, not a tenant's."
    )] = False,
) -> None:
    """Make a key and print it once; only its hash is stored."""
    if not tenant.strip() or len(tenant) > 100:
        typer.echo("error: --tenant must be 1 to 100 characters", err=True)
        raise typer.Exit(2)
    path = _path(file)
    records = _records(path)
    if if_none and any(not r.revoked for r in records):
        typer.echo(f"{path} already holds a key; none made")
        return
    key_id, key = new_key()
    now = datetime.now(UTC)
    expires = None if expires_days is None else (now + timedelta(days=expires_days)).isoformat()
    records.append(KeyRecord(key_id, tenant, digest(key), now.isoformat(), expires, operator=operator))
    write_records(path, records)
    typer.echo(f"API key {key_id} for tenant {tenant!r} (shown once, keep it secret):\n\n    {key}\n")
    typer.echo(f"Use it as:  curl -H 'Authorization: Bearer {key}' http://HOST:8000/check-actions ...")


@keys.command(name="list")
def list_keys(file: KeysFile = None) -> None:
    """The keys' ids, tenants and state (never the keys)."""
    for r in _records(_path(file)):
        state = "revoked" if r.revoked else f"expires {r.expires}" if r.expires else "active"
        role = "\toperator" if r.operator else ""
        typer.echo(f"{r.id}\t{r.tenant}\tcreated {r.created}\t{state}{role}")


@keys.command()
def revoke(
    key_id: Annotated[str, typer.Argument(help="The key's id, as `list` shows it.")], file: KeysFile = None
) -> None:
    """Revoke a key; the gateway refuses it from its next request on."""
    path = _path(file)
    records = _records(path)
    if not any(r.id == key_id for r in records):
        typer.echo(f"error: no key {key_id} in {path}", err=True)
        raise typer.Exit(2)
    write_records(path, [KeyRecord(**{**r.__dict__, "revoked": True}) if r.id == key_id else r for r in records])
    typer.echo(f"revoked {key_id}")


def register(app: typer.Typer) -> None:
    app.add_typer(keys, name="keys")
