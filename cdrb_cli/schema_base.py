"""Base class of every pydantic model stored in an artifact."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationInfo, model_validator


class Record(BaseModel):
    """A strict, immutable record: unknown fields and non-finite numbers are errors, except (for unknown fields)
    when reading a newer *minor* schema
    version, where the reader passes ``context={"lenient": True}`` and unknown fields are dropped (minor versions
    only ever add optional fields, see docs/format.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True, protected_namespaces=(), allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _drop_unknown_when_lenient(cls, data: Any, info: ValidationInfo) -> Any:
        if info.context and info.context.get("lenient") and isinstance(data, dict):
            known = set(cls.model_fields) | {f.alias for f in cls.model_fields.values() if f.alias}
            return {k: v for k, v in data.items() if k in known}
        return data
