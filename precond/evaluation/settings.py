"""Where the full development data lives: `PRECOND_DATA_DIR`, or `../shared/data` beside the checkout.

Only the evaluation (`precond eval`), the benchmarks and `examples/build.py` read it; the test suite runs on
the small subsets in tests/fixtures, so a fresh clone passes its tests with nothing beside it.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA_DIR = ROOT.parent / "shared" / "data"


class DataMissing(FileNotFoundError):
    """The development data is not where the settings say; the message names the path and the setting."""


class DataSettings(BaseSettings):
    """The evaluation data (`precond/evaluation/`, `precond eval`, `bench/`)."""

    model_config = SettingsConfigDict(env_prefix="PRECOND_", extra="ignore", frozen=True)

    data_dir: Path | None = Field(
        default=None,
        description="Directory holding the development data (`sgd/*.json`, `alfworld/`) that `precond eval`, "
        "the benchmarks and `examples/build.py` read. Unset: `../shared/data` beside the checkout. The test "
        "suite never reads it (it uses tests/fixtures).",
    )

    @property
    def root(self) -> Path:
        return self.data_dir or DEFAULT_DATA_DIR

    def path(self, *parts: str) -> Path:
        """`root/parts...`, which must exist; else DataMissing naming the path and `PRECOND_DATA_DIR`."""
        path = self.root.joinpath(*parts)
        if not path.exists():
            raise DataMissing(missing_message(path))
        return path


def missing_message(path: Path) -> str:
    return (
        f"evaluation data not found: {path} does not exist. Put the development data (sgd/, alfworld/) in "
        f"{DEFAULT_DATA_DIR} or set PRECOND_DATA_DIR to the directory that holds it (docs/configuration.md)."
    )


def data_path(*parts: str) -> Path:
    return DataSettings().path(*parts)
