"""The method registry as plugins and the method modules import it (:mod:`cdrb_cli.method_registry`, which the
stage configs below the methods also read)."""

from cdrb_cli.method_registry import (
    DEFAULT_METHOD,
    METHODS,
    BufferInfo,
    MethodEntry,
    MethodParams,
    StartWeightParams,
    start_weighted,
)

__all__ = [
    "DEFAULT_METHOD",
    "METHODS",
    "BufferInfo",
    "MethodEntry",
    "MethodParams",
    "StartWeightParams",
    "start_weighted",
]
