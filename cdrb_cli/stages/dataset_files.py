"""`cdrb import npz`: an outside dataset file as a demos artifact, read by the environment family whose format it
is (``EnvFamily.read_dataset``; e.g. OGBench's ``.npz`` files)."""

from __future__ import annotations

import time
from pathlib import Path

from cdrb_cli.errors import BadInput


def env_for_import(env: str):
    """The EnvSpec an import's ``--env`` names; an unknown id is one line naming the flag (the registry's own line
    offers --maze-map, which no import takes)."""
    from cdrb_cli.envs.registry import make_spec

    try:
        return make_spec(env)
    except BadInput as exc:
        if not exc.message.startswith("unknown environment"):
            raise
        raise BadInput(f"--env {env!r}: not an environment of cdrb", hint="`cdrb envs` lists them") from None


def import_file(path: Path, out: Path, env: str | None = None, valid_fraction: float = 0.1, seed: int = 0):
    """Read the dataset file ``path`` for ``env`` (default: the environment its name says) and write it as a demos
    artifact."""
    from cdrb_cli.configs import CollectConfig
    from cdrb_cli.envs.registry import FAMILIES, family_of
    from cdrb_cli.stages.collect import write_demos

    t0, path = time.time(), Path(path)
    if env is None:
        env = next((e for fam in FAMILIES.entries() if (e := fam.dataset_env(path))), None)
        if env is None:
            raise BadInput(
                f"{path}: its name says no environment (no family reads files so named)",
                hint="name the environment with --env (`cdrb envs`)",
            )
    spec = env_for_import(env)
    read = family_of(spec).read_dataset(spec, path)
    if read is None:
        raise BadInput(f"--env {spec.id}: its environments read no dataset files", hint="see docs/cli.md")
    states, actions, goals, success, source = read
    config = CollectConfig(env=spec.id, episodes=len(states), expert=source, valid_fraction=valid_fraction, seed=seed)
    return write_demos(out, spec, config, states, actions, goals, [-1] * len(states), success, {}, t0, source=str(path))
