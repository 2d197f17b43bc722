"""Demonstrations that came from a Minari dataset (`cdrb import minari`): their provenance as the demos
artifact's "expert" record. There is nothing to roll out: `cdrb collect --expert minari-dataset` is refused."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field

from cdrb_cli.envs.family import ExpertConfig, ExpertEntry
from cdrb_cli.envs.registry import EXPERTS
from cdrb_cli.errors import BadInput


class MinariSourceConfig(ExpertConfig):
    """A Minari dataset imported by `cdrb import minari`: which one, and the sha256 of each of its files."""

    kind: Literal["minari-dataset"] = "minari-dataset"
    dataset_id: str
    minari_version: str = Field(description="the Minari version that wrote the dataset")
    algorithm_name: str | None = Field(None, description="who produced the dataset's episodes, as it says")
    gym_env_id: str | None = Field(None, description="the dataset's environment (its env_spec id)")
    files: dict[str, str] = Field(description="sha256 of every file of the dataset, by path inside its folder")
    success_rule: str = Field(
        "cdrb", description="how episodes/success was derived: cdrb's success test on the imported states"
    )

    def describe(self) -> str:
        return (
            f"Minari dataset {self.dataset_id} (written by Minari {self.minari_version}"
            + (f", env {self.gym_env_id}" if self.gym_env_id else "")
            + (f", by {self.algorithm_name}" if self.algorithm_name else "")
            + f"; {len(self.files)} files, sha256 recorded)"
        )


def _no_rollouts(spec, config):
    raise BadInput(
        "--expert minari-dataset: imported demonstrations cannot be rolled out", hint="use `cdrb import minari`"
    )


def _configure(policy: Path | None):
    raise BadInput("--expert minari-dataset: use `cdrb import minari DATASET --out demos.h5`", hint="see docs/cli.md")


EXPERTS.register(ExpertEntry(MinariSourceConfig, _no_rollouts, _configure, "episodes imported from a Minari dataset"))
