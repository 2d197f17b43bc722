"""The task side's registries and the environment catalogue.

* :data:`FAMILIES`: environment families (:class:`cdrb_cli.envs.family.EnvFamily` instances) by name;
* :data:`EXPERTS`: demonstrators by name (a family lists the ones it accepts);
* :data:`CONTROLLERS`: plan-executing controllers by name (likewise).

An env id (``maze-tight``) belongs to the family that lists it in ``env_ids()``; a file (a maze map) to the
family whose ``spec_from_file`` reads it. :func:`make_spec` and :func:`list_envs` are what the CLI calls.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cdrb_cli.envs.family import ControllerEntry, EnvFamily, ExpertEntry
from cdrb_cli.envs.spec import FAMILY_MODULES, SCENES, EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.registry import Registry


class FamilyRegistry(Registry[EnvFamily]):
    """The families; registering one also registers its scene type (:data:`~cdrb_cli.envs.spec.SCENES`), by
    which an EnvSpec reads its family's part."""

    def register(self, entry: EnvFamily, replace: bool = False) -> EnvFamily:
        super().register(entry, replace)
        SCENES.register(entry.scene_type, replace=True)
        return entry

    def unregister(self, name: str) -> None:
        super().unregister(name)
        SCENES.unregister(name)


FAMILIES = FamilyRegistry("environment family", FAMILY_MODULES, EnvFamily)
EXPERTS: Registry[ExpertEntry] = Registry(
    "expert",
    {
        "planner": "cdrb_cli.envs.pointmaze.expert",
        "fetch-scripted": "cdrb_cli.envs.fetch.expert",
        "sac": "cdrb_cli.experts.sac",
        "minari-dataset": "cdrb_cli.experts.minari",
        "ogbench-noisy": "cdrb_cli.envs.ogbench.expert",
        "ogbench-dataset": "cdrb_cli.envs.ogbench.dataset",
    },
    ExpertEntry,
)
CONTROLLERS: Registry[ControllerEntry] = Registry(
    "controller",
    {
        "pd": "cdrb_cli.envs.pointmaze.controllers",
        "inverse-dynamics": "cdrb_cli.envs.pointmaze.controllers",
        "waypoint": "cdrb_cli.envs.pointmaze.controllers",
        "fetch-track": "cdrb_cli.envs.fetch.controllers",
        "fetch-push-path": "cdrb_cli.envs.fetch.controllers",
        "fetch-official": "cdrb_cli.envs.fetch.official",
        "pursuit": "cdrb_cli.envs.ogbench.controllers",
    },
    ControllerEntry,
)


def family_of(spec: EnvSpec) -> EnvFamily:
    """The family that made ``spec``."""
    return FAMILIES.get(spec.family)


def _env_index() -> dict[str, EnvFamily]:
    index: dict[str, EnvFamily] = {}
    for fam in FAMILIES.entries():
        for env_id in fam.env_ids():
            index.setdefault(env_id, fam)
    return index


def make_spec(env_id: str | None, map_file: str | Path | None = None) -> EnvSpec:
    """The EnvSpec of a registered env id, or of a map file (``--maze-map``; then ``env_id`` may be None or
    ``map``)."""
    if map_file is not None:
        if env_id not in (None, "map", "custom"):
            raise BadInput(f"ENV {env_id!r} and --maze-map both given", hint="pass one of them (or ENV 'map')")
        path = Path(map_file)
        for fam in FAMILIES.entries():
            spec = fam.spec_from_file(path)
            if spec is not None:
                return spec
        raise BadInput(f"--maze-map {path}: no environment family reads this file", hint="pass a maze map")
    index = _env_index()
    if env_id is None:
        raise BadInput("no environment given", hint=f"pass one of {', '.join(index)} or --maze-map FILE")
    if env_id not in index:
        raise BadInput(f"unknown environment {env_id!r}", hint=f"choose one of {', '.join(index)}, or --maze-map FILE")
    return index[env_id].make_spec(env_id)


def describe(spec: EnvSpec, description: str) -> dict[str, Any]:
    """One row of `cdrb envs`: the common facts of a spec, then its family's own."""
    return {
        "id": spec.id,
        "family": spec.family,
        "description": description,
        "obs_dim": spec.obs_dim,
        "action_dim": spec.action_dim,
        "goal_dim": spec.goal_dim,
        "horizon": spec.horizon,
        "plan_stride": spec.plan_stride,
        "plan_env_steps": spec.plan_env_steps,
        "episode_limit": spec.episode_limit,
        "success_radius": spec.success_radius,
        "protocols": family_of(spec).protocols(),
        **family_of(spec).details(spec),
    }


def list_envs() -> list[dict[str, Any]]:
    """A row per registered env id, family by family."""
    return [describe(fam.make_spec(i), text) for fam in FAMILIES.entries() for i, text in fam.env_ids().items()]
