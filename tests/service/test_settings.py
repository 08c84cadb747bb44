"""Every service setting is described once, in its field: docs/service.md lists each as the
code has it (environment variable, default, meaning)."""

from __future__ import annotations

from pathlib import Path

from service.settings import Settings, settings_table

DOCS = Path(__file__).resolve().parents[2] / "docs" / "service.md"


def test_docs_list_every_setting_as_the_code_has_it() -> None:
    docs = DOCS.read_text()
    assert settings_table() in docs, "docs/service.md's settings table is stale: python -m service.settings"
    for name, field in Settings.model_fields.items():
        assert f"`PHD_{name.upper()}`" in docs and field.description


def test_the_table_shows_the_defaults() -> None:
    rows = {row.split(" | ")[0].strip("| `"): row.split(" | ")[1] for row in settings_table().splitlines()[2:]}
    assert rows["PHD_MAX_UPLOAD_BYTES"] == "1 GiB" and rows["PHD_MAX_JSON_BYTES"] == "32 MiB"
    assert rows["PHD_WORKERS"] == str(Settings.model_fields["workers"].default)
    assert rows["PHD_ASYNC_THRESHOLD"] == "2e7" and rows["PHD_API_KEY"] == "unset"
    assert rows["PHD_EXECUTOR"] == "`local`" and rows["PHD_UPLOAD_WAIT"] == "30"
