"""The committed JSON Schemas must match the pydantic models, and validate real manifests."""

from __future__ import annotations

import json
import os
from pathlib import Path

import jsonschema
import pytest

from cdrb_cli import artifacts
from cdrb_cli.artifacts import schema
from tests.factories import KINDS, build

SCHEMAS = Path(__file__).resolve().parent.parent / "schemas"


def test_committed_schemas_do_not_drift():
    stale = schema.drift(SCHEMAS)
    assert not stale, f"run `cdrb schema export schemas` (stale: {stale})"


def test_drift_is_detected(tmp_path):
    schema.export(tmp_path)
    assert schema.drift(tmp_path) == []
    victim = tmp_path / "demos.v2.schema.json"
    victim.write_text(victim.read_text().replace('"episodes"', '"episodez"', 1))
    assert schema.drift(tmp_path) == [victim.name]


@pytest.mark.parametrize("kind", KINDS)
def test_manifests_validate_against_committed_schema(kind):
    manifest, _ = build(kind)
    major = artifacts.SCHEMA_VERSIONS[kind].split(".")[0]
    doc = json.loads((SCHEMAS / f"{kind}.v{major}.schema.json").read_text())
    jsonschema.validate(json.loads(manifest.model_dump_json()), doc)
    bad = json.loads(manifest.model_dump_json())
    bad["seed"] = "not an int"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, doc)


def test_cli_export_and_check(tmp_path, cdrb):
    r = cdrb("schema", "export", tmp_path)
    assert r.returncode == 0, r.stderr
    assert len(r.stdout.split()) == len(KINDS)
    assert cdrb("schema", "check", tmp_path).returncode == 0
    (tmp_path / "eval.v2.schema.json").write_text("{}")
    r = cdrb("schema", "check", tmp_path)
    assert r.returncode == 1 and "eval.v2.schema.json" in r.stderr
    # a schema file read as every input file is: bytes that are not text, or a FIFO, are one line, not a hang
    (tmp_path / "eval.v2.schema.json").write_bytes(b"\xff\xfe{}")
    r = cdrb("schema", "check", tmp_path)
    assert r.returncode == 2 and "eval.v2.schema.json: not a text file" in r.stderr and r.stderr.count("\n") == 1
    (tmp_path / "eval.v2.schema.json").unlink()
    os.mkfifo(tmp_path / "eval.v2.schema.json")
    r = cdrb("schema", "check", tmp_path)
    assert r.returncode == 2 and "not a regular file" in r.stderr


def test_schema_commands_refuse_a_file_or_a_missing_folder_in_one_line(tmp_path, cdrb):
    afile = tmp_path / "f.txt"
    afile.write_text("mine\n")
    for args, said in (
        (["export", afile], "is a file"),
        (["export", "/proc/cdrb-schemas"], "cannot make the folder"),
        (["check", tmp_path / "nope"], "no such folder"),
        (["check", afile], "is not a folder"),
    ):
        r = cdrb("schema", *args)
        assert r.returncode == 2 and said in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)
    assert afile.read_text() == "mine\n" and not (tmp_path / "nope").exists()
    r = cdrb("schema", "export", tmp_path / "s")
    assert r.returncode == 0 and cdrb("schema", "check", tmp_path / "s").returncode == 0
