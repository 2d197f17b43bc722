"""JSON Schema export of the artifact manifests (one file per kind and major version)."""

from __future__ import annotations

import json
from pathlib import Path

from cdrb_cli.artifacts.core import atomic_path, parse_version
from cdrb_cli.artifacts.kinds import KINDS, SCHEMA_VERSIONS
from cdrb_cli.errors import BadInput


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
    """Write every schema file into ``folder`` (made where missing), each atomically; a path that is a file or a
    folder that cannot be made or written is a one-line error."""
    from cdrb_cli.artifacts.outputs import check_writable

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise BadInput(f"{folder}: is a file", hint="name a folder to write the schema files into")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInput(
            f"{folder}: cannot make the folder ({exc.strerror or type(exc).__name__})", hint="choose a writable folder"
        ) from None
    check_writable(folder, "schema export", folder)
    written = []
    for name, text in schemas().items():
        with atomic_path(folder / name) as tmp:
            tmp.write_text(text)
        written.append(folder / name)
    return written


def drift(folder: str | Path) -> list[str]:
    """Names of schema files that are missing from ``folder`` or differ from the models; a ``folder`` that is not
    one is a one-line error."""
    folder = Path(folder)
    if not folder.is_dir():
        raise BadInput(
            f"{folder}: {'is not a folder' if folder.exists() else 'no such folder'}",
            hint="give the folder of the schema files",
        )
    stale = []
    for name, text in schemas().items():
        path = folder / name
        if not path.exists() or _read(path) != text:
            stale.append(name)
    return stale


def _read(path: Path) -> str:
    """A committed schema file's text, through the guarded reader every input file passes (a FIFO, a device or a
    file that is not UTF-8 is one line of error, not a hang or a traceback)."""
    from cdrb_cli.files import read_input_text

    return read_input_text(path, "", 16 * 2**20, "schema file", hint="run `cdrb schema export` to write it again")
