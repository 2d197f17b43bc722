"""JSON Schema export of the artifact manifests (one file per kind and major version)."""

from __future__ import annotations

import json
from pathlib import Path

from cdrb_cli.artifacts.core import atomic_path, parse_version
from cdrb_cli.artifacts.kinds import KINDS, SCHEMA_VERSIONS


def schemas() -> dict[str, str]:
    """File name -> JSON text of every kind's manifest schema."""
    out = {}
    for kind, cls in KINDS.items():
        major, _ = parse_version(SCHEMA_VERSIONS[kind])
        schema = cls.manifest_cls.model_json_schema()
        schema = {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": f"cdrb/{kind}.v{major}.schema.json",
            "x-cdrb-kind": kind,
            "x-cdrb-schema-version": SCHEMA_VERSIONS[kind],
            **schema,
        }
        out[f"{kind}.v{major}.schema.json"] = json.dumps(schema, indent=2, sort_keys=True) + "\n"
    return out


def export(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in schemas().items():
        with atomic_path(folder / name) as tmp:
            tmp.write_text(text)
        written.append(folder / name)
    return written


def drift(folder: str | Path) -> list[str]:
    """Names of schema files that are missing from ``folder`` or differ from the models."""
    folder = Path(folder)
    stale = []
    for name, text in schemas().items():
        path = folder / name
        if not path.exists() or path.read_text() != text:
            stale.append(name)
    return stale
