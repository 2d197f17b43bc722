"""Minari datasets in and out: `cdrb import minari` and `cdrb export --minari`.

Mapping (one episode of T steps):

| cdrb demos                      | Minari episode                                               |
|---------------------------------|--------------------------------------------------------------|
| steps/observations (T+1 rows)   | observations["observation"] (T+1)                            |
| steps/actions (T+1, last zero)  | actions (T)                                                  |
| steps/desired_goals (T+1)       | observations["desired_goal"] (T+1)                           |
| (the state's goal dims)         | observations["achieved_goal"] (T+1)                          |
| episodes/success                | infos["success"] (T+1) on export; on import always cdrb's    |
|                                 | success test on the states (a dense reward says nothing)     |
| episodes/seed                   | the episode's seed (-1 when the dataset has none)            |
| env (EnvSpec)                   | env_spec: the family's gymnasium equivalent (`to_gym`), or   |
|                                 | none (no gymnasium equivalent): the description names the env |

cdrb never downloads: a dataset id is looked up in Minari's local folder (``MINARI_DATASETS_PATH``, default
~/.minari/datasets), or a dataset folder is given by path.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from cdrb_cli import __version__, artifacts, ui
from cdrb_cli.artifacts.core import MAX_MAGNITUDE, in_bounds
from cdrb_cli.artifacts.outputs import check_output_folder, locked
from cdrb_cli.errors import BadInput, OutputExists
from cdrb_cli.files import new_folder, replace_folder, temp_folder_at

#: the description tag that names a cdrb environment in an exported dataset without a gymnasium env_spec
ENV_TAG = "cdrb-env:"


def _root() -> Path:
    return Path(os.environ.get("MINARI_DATASETS_PATH") or Path.home() / ".minari" / "datasets")


def _minari():
    try:
        import minari
    except ImportError:
        raise BadInput("Minari is not installed", hint='pip install "cdrb-cli[minari]"') from None
    return minari


def locate(source: str) -> Path:
    """The ``data`` folder (metadata.json + main data) of a dataset given by id or by path."""
    p = Path(source).expanduser()
    candidates = [p, p / "data"] if p.exists() else [_root() / source / "data"]
    for c in candidates:
        if (c / "metadata.json").is_file():
            return c
    if p.exists():
        raise BadInput(
            f"{source}: not a Minari dataset folder (no metadata.json in it or in its data/)",
            hint="give the dataset's folder",
        )
    raise BadInput(
        f"{source}: no such Minari dataset in {_root()} (cdrb never downloads)",
        hint=f"`minari download {source}` first, set MINARI_DATASETS_PATH, or give the dataset's folder",
    )


#: a Minari dataset folder cdrb reads: at most this many files, metadata this large, HDF5 objects per data file
MAX_DATASET_FILES = 10_000
MAX_METADATA_BYTES = 1 << 20
MAX_DATASET_OBJECTS = 5_000_000


def check_dataset_folder(folder: Path, source: str) -> None:
    """Everything in a dataset folder is checked before Minari opens it: only regular files and folders (no link,
    which could point outside the dataset or at a device, no FIFO), a bounded number of them, a small
    metadata.json, and each HDF5 file by the artifact reader's rules (no links out, no virtual or external storage,
    declared sizes within what the file holds)."""
    import stat

    from cdrb_cli.artifacts.core import check_foreign_h5

    count = 0
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=False):
        for name in [*dirnames, *filenames]:
            count += 1
            p = Path(dirpath) / name
            mode = p.lstat().st_mode
            if stat.S_ISLNK(mode) or not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
                what = "a link" if stat.S_ISLNK(mode) else "not a regular file"
                raise BadInput(
                    f"{source}: {ui.plain(str(p.relative_to(folder)), 120)} is {what}",
                    hint="a Minari dataset folder holds regular files only",
                )
            if count > MAX_DATASET_FILES:
                raise BadInput(f"{source}: more than {MAX_DATASET_FILES:,} files", hint="give the dataset's own folder")
    for meta in folder.rglob("metadata.json"):
        if meta.stat().st_size > MAX_METADATA_BYTES:
            raise BadInput(
                f"{source}: {meta.relative_to(folder)} is larger than {MAX_METADATA_BYTES >> 10} KiB",
                hint="the dataset is damaged or hostile",
            )
    for data in sorted(folder.rglob("*.hdf5")) + sorted(folder.rglob("*.h5")):
        try:
            check_foreign_h5(data, MAX_DATASET_OBJECTS)
        except BadInput as exc:
            raise BadInput(f"{source}: {exc.message}", hint=exc.hint) from None
    for meta in folder.rglob("metadata.json"):
        _check_episode_count(meta, source)


def _check_episode_count(meta: Path, source: str) -> None:
    """The episode count a Minari metadata.json declares is the number of episodes its data file holds: Minari
    allocates arrays by the declared count (a billion fills the memory before anything is read) and reads only that
    many episodes (a smaller count drops the rest silently)."""
    import json

    import h5py

    data = meta.parent / "main_data.hdf5"
    try:
        declared = json.loads(meta.read_text()).get("total_episodes")
    except (ValueError, AttributeError, RecursionError, UnicodeDecodeError):
        return  # not a table of metadata: Minari's own reading says what is wrong
    if not data.is_file() or type(declared) is not int:
        return
    with h5py.File(data, "r") as f:
        held = sum(1 for name in f.keys() if name.startswith("episode_"))
    if declared != held:
        raise BadInput(
            f"{source}: {meta.name} declares {str(declared)[:30]} episodes, but {data.name} holds {held}",
            hint="the dataset is damaged; re-download or re-create it",
        )


def _sha_files(folder: Path) -> dict[str, str]:
    return {str(f.relative_to(folder)): artifacts.sha256_file(f) for f in sorted(folder.rglob("*")) if f.is_file()}


def _spec_for(dataset, source: str, env: str | None):
    """The cdrb EnvSpec of a dataset: ``--env`` when given, else from its env_spec (every family is asked)."""
    from cdrb_cli.envs.registry import FAMILIES, make_spec

    if env is not None:
        from cdrb_cli.stages.dataset_files import env_for_import

        return env_for_import(env)
    gym_spec = dataset.env_spec
    if gym_spec is not None:
        name = re.sub(r"[^A-Za-z0-9_.-]+", "-", dataset.spec.dataset_id).strip("-")
        for fam_name in FAMILIES.names():
            spec = FAMILIES.get(fam_name).from_gym(gym_spec.id, dict(gym_spec.kwargs or {}), name)
            if spec is not None:
                return spec
    # a dataset cdrb exported for an environment no gymnasium registry has names it in its description
    m = re.search(re.escape(ENV_TAG) + r"\s*([\w.-]+)", dataset.storage.metadata.get("description") or "")
    if m:
        return make_spec(m.group(1))
    if gym_spec is None:
        raise BadInput(f"{source}: the dataset records no environment (env_spec)", hint="name it with --env ENV")
    raise BadInput(
        f"{source}: environment {gym_spec.id} has no cdrb equivalent (no environment family recognises it)",
        hint="name a matching cdrb environment with --env ENV",
    )


def _check_spaces(dataset, spec, source: str) -> None:
    """The dataset's spaces fit ``spec``: goal-dict observations of its dims, actions of its dims."""
    space = dataset.observation_space
    keys = set(getattr(space, "spaces", {}) or {})
    if not {"observation", "desired_goal"} <= keys:
        raise BadInput(
            f"{source}: observations are not a goal dict with 'observation' and 'desired_goal'",
            hint="cdrb imports goal-conditioned datasets (dict observations with the goal)",
        )
    for key, want in (("observation", spec.obs_dim), ("desired_goal", spec.goal_dim)):
        shape = space.spaces[key].shape
        if shape != (want,):
            raise BadInput(
                f"{source}: {key} has shape {shape}, {spec.id} states need ({want},)",
                hint="name the right environment with --env",
            )
    act = getattr(dataset.action_space, "shape", None)
    if act != (spec.action_dim,):
        raise BadInput(f"{source}: actions have shape {act}, {spec.id} takes ({spec.action_dim},)", hint="--env")


def import_minari(source: str, out: Path, env: str | None = None, valid_fraction: float = 0.1, seed: int = 0):
    """Read a Minari dataset and write it as a demos artifact for the matching cdrb environment."""
    from cdrb_cli.configs import CollectConfig
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.experts.minari import MinariSourceConfig
    from cdrb_cli.stages.collect import write_demos

    minari = _minari()
    t0 = time.time()
    data = locate(source)
    folder = data.parent if data.name == "data" else data
    if Path(out).resolve().is_relative_to(folder.resolve()):
        raise BadInput(
            f"--out {out}: inside the dataset being imported ({folder})",
            hint="write the demos artifact outside the dataset's folder",
        )
    check_dataset_folder(folder, source)
    try:
        dataset = minari.MinariDataset(data)
    except Exception as exc:  # a damaged or foreign folder: Minari's own complaint, on one line
        raise BadInput(
            f"{source}: Minari cannot open it ({type(exc).__name__}: {exc})", hint="check the dataset"
        ) from None
    spec = _spec_for(dataset, source, env)
    family = family_of(spec)
    try:  # per-episode metadata: the reset seed, where the dataset recorded it
        ep_seeds = {int(m["id"]): m.get("seed") for m in dataset.storage.get_episode_metadata(dataset.episode_indices)}
    except Exception:
        ep_seeds = {}
    _check_spaces(dataset, spec, source)
    states, actions, goals, seeds, success = [], [], [], [], []
    ids = [str(i) for i in dataset.episode_indices]  # in the order they are read: names the one a read fails on
    where = f"{source}: episode {ui.plain(ids[0], 40)}" if ids else source
    try:  # a missing array, text where numbers belong: Minari and numpy raise their own errors
        with ui.progress() as bar:
            task = bar.add_task(
                ui.plain(f"import {dataset.spec.dataset_id}", 60), total=dataset.total_episodes, info=""
            )
            for ep in dataset.iterate_episodes():
                where = f"{source}: episode {ui.plain(str(ep.id), 40)}"
                S, A, G = _episode_arrays(ep, where, spec, source)
                states.append(S)
                actions.append(np.concatenate([A, np.zeros((1, spec.action_dim))]))
                goals.append(G)
                ep_seed = ep_seeds.get(int(ep.id))
                seeds.append(-1 if ep_seed is None else int(ep_seed))
                success.append(bool(family.success(spec, S, G).any()))
                bar.update(task, completed=len(states), info=f"success {np.mean(success):.1%}")
                where = f"{source}: episode {ui.plain(ids[len(states)], 40)}" if len(states) < len(ids) else source
    except (KeyError, ValueError, TypeError, IndexError, OSError) as exc:
        said = " ".join(str(exc).split())[:160]
        raise BadInput(
            f"{where}: cannot be read ({type(exc).__name__}: {said})", hint="the dataset is damaged"
        ) from None
    if not states:
        raise BadInput(f"{source}: the dataset has no episodes", hint="give another dataset")
    meta = dataset.storage.metadata
    source_cfg = MinariSourceConfig(
        dataset_id=str(dataset.spec.dataset_id),
        minari_version=str(meta.get("minari_version", "?")),
        algorithm_name=meta.get("algorithm_name"),
        gym_env_id=dataset.env_spec.id if dataset.env_spec is not None else None,
        files=_sha_files(data.parent if data.name == "data" else data),
    )
    E = len(states)
    config = CollectConfig(env=spec.id, episodes=E, expert=source_cfg, valid_fraction=valid_fraction, seed=seed)
    return write_demos(out, spec, config, states, actions, goals, seeds, success, {}, t0, source=source)


def _episode_arrays(ep, where: str, spec, source: str):
    """An episode's states (T, obs), actions (T-1, act) and goals (T, goal) as float64, each checked against
    ``spec``: a one-line error naming the episode for any that does not fit."""
    obs = ep.observations
    if not isinstance(obs, dict) or not {"observation", "desired_goal"} <= set(obs):
        raise BadInput(
            f"{source}: observations are not a goal dict with 'observation' and 'desired_goal'",
            hint="cdrb imports goal-conditioned datasets (dict observations with the goal)",
        )
    S, G = np.asarray(obs["observation"], np.float64), np.asarray(obs["desired_goal"], np.float64)
    A = np.asarray(ep.actions, np.float64)
    if S.ndim != 2 or len(S) < 2:
        raise BadInput(f"{where}: fewer than 2 states", hint="every episode needs a start and a step")
    if len(G) != len(S) or len(A) != len(S) - 1:
        raise BadInput(
            f"{where}: {len(S)} observations, {len(G)} goals and {len(A)} actions (expected T, T and T-1)",
            hint="the dataset is damaged",
        )
    for arr in (S, G, A):
        if not np.isfinite(arr).all():
            raise BadInput(f"{where}: NaN or infinite values", hint="the dataset is damaged")
        if not in_bounds(arr):
            raise BadInput(f"{where}: values beyond +-{MAX_MAGNITUDE:g}", hint="the dataset is damaged")
    A = A.reshape(len(S) - 1, -1)
    for what, arr, want in (("observation", S, spec.obs_dim), ("desired_goal", G, spec.goal_dim)):
        if arr.ndim != 2 or arr.shape[1] != want:
            raise BadInput(
                f"{where}: {what} has shape {arr.shape}, {spec.id} states need {want} dims",
                hint="name the right environment with --env",
            )
    if A.shape[1] != spec.action_dim:
        raise BadInput(f"{source}: actions have {A.shape[1]} dims, {spec.id} takes {spec.action_dim}", hint="--env")
    return S, A, G


# ------------------------------------------------------------------------------------------------ export
DATASET_ID = re.compile(r"^(?:[A-Za-z0-9_.-]+/)*[A-Za-z0-9_.-]+-v\d+$")


def dataset_id_for(name: str) -> str:
    """``name`` as a Minari dataset id (``[namespace/]name-vN``; ``-v0`` is added when no version is given)."""
    full = name if re.search(r"-v\d+$", name) else f"{name}-v0"
    parts = full.split("/")
    dots = any(not part[:1].isalnum() for part in parts)  # ".", "..", ".-v0", "..-v0": not names Minari takes
    if not DATASET_ID.match(full) or dots or len(full) > 200 or len(parts) > 8:
        raise BadInput(
            f"--minari {ui.plain(repr(name), 80)}: not a dataset name (letters, digits, . _ -, optional namespace/, "
            "optional -vN; at most 200 characters)",
            hint="e.g. cdrb/maze-tight-expert-v0",
        )
    return full


def export_minari(demos, name: str, root: Path | None = None, force: bool = False) -> Path:
    """Write ``demos`` as a Minari dataset named ``name`` under ``root`` (default: Minari's local folder);
    returns the dataset's folder. Written in a temporary folder beside it and renamed into place."""
    from cdrb_cli.envs.registry import family_of

    _minari()  # installed, or one line saying how
    import gymnasium
    from minari.data_collector.episode_buffer import EpisodeBuffer

    dataset_id = dataset_id_for(name)
    # absolute: the env's files are written under it, and gymnasium reads a relative XML path as one in its assets
    root = _export_root(root, dataset_id)
    final = root / dataset_id
    check_output_folder(final, f"--minari {dataset_id}", [getattr(demos, "path", None)])
    _check_export_target(final, root, dataset_id, force)
    spec = demos.manifest.env
    family = family_of(spec)
    env_spec = family.to_gym(spec)
    episodes = []
    for e in range(demos.n_episodes):
        S, A = demos.episode(e)
        s0, n = int(demos.episode_start[e]), int(demos.episode_length[e])
        G = demos.desired_goals[s0 : s0 + n]
        ok = family.success(spec, S, G)
        obs = {
            "achieved_goal": np.asarray(S[:, spec.goal_dims], np.float64),
            "desired_goal": np.asarray(G, np.float64),
            "observation": np.asarray(S, np.float64),
        }
        T = n - 1
        episodes.append(
            EpisodeBuffer(
                id=e,
                seed=int(demos.episode_seed[e]) if demos.episode_seed[e] >= 0 else None,
                observations=obs,
                actions=np.asarray(A[:T], np.float32),
                rewards=[float(x) for x in ok[1:]],
                terminations=[False] * T,
                truncations=[False] * (T - 1) + [True] if T > 0 else [],
                infos={"success": np.asarray(ok, dtype=bool)},
            )
        )
    box = lambda d: gymnasium.spaces.Box(-np.inf, np.inf, (d,), np.float64)  # noqa: E731
    obs_space = gymnasium.spaces.Dict(
        {"achieved_goal": box(spec.goal_dim), "desired_goal": box(spec.goal_dim), "observation": box(spec.obs_dim)}
    )
    act_space = gymnasium.spaces.Box(-1.0, 1.0, (spec.action_dim,), np.float32)
    expert = demos.manifest.config.expert
    description = (
        f"Demonstrations exported by cdrb {__version__} from a demos artifact (sha256 {demos.sha256}); "
        f"{ENV_TAG} {spec.id}; demonstrator: {expert.kind}; success: cdrb's test (within {spec.success_radius} of "
        "the goal), per step in infos['success'] and as the sparse reward."
    )
    with new_folder(final.parent), locked(final, "--minari"):
        _check_export_target(final, root, dataset_id, force)  # again, now that no other export can be writing it
        return _write_dataset(final, root, dataset_id, episodes, env_spec, expert, obs_space, act_space, description)


def _export_root(root: Path | None, dataset_id: str) -> Path:
    """The absolute datasets folder an export writes under (``--root``, else ``MINARI_DATASETS_PATH`` or Minari's
    default), checked before any work: no link loop on the way to the dataset's folder, and the nearest folder
    that exists on that way is a folder a file can be made in (one-line errors naming the flag or variable)."""
    from cdrb_cli.artifacts.outputs import check_can_make

    given = "--root" if root is not None else ("MINARI_DATASETS_PATH" if os.environ.get("MINARI_DATASETS_PATH")
                                               else "Minari's datasets folder")  # fmt: skip
    root = (Path(root) if root is not None else _root()).absolute()
    hint = "give the folder Minari datasets live in" + (": --root DIR" if given != "--root" else "")
    try:
        (root / dataset_id).resolve()
    except (RuntimeError, OSError) as exc:  # a link loop (RuntimeError before Python 3.13), a name too long
        raise BadInput(f"{given} {root}: cannot be followed ({exc})", hint=hint) from None
    if root.exists() and not root.is_dir():
        raise BadInput(f"{given} {root}: not a folder", hint=hint)
    check_can_make(root / dataset_id, given, root, hint)
    return root


def _check_export_target(final: Path, root: Path, dataset_id: str, force: bool) -> None:
    """The dataset folder an export may write: not an existing dataset unless ``force``, never a dataset nested
    in another (its parent's --force would delete it) nor one holding others, nothing but a plain folder."""
    for parent in final.relative_to(root).parents:
        if parent != Path(".") and (root / parent / "data" / "metadata.json").exists():
            raise BadInput(
                f"--minari {dataset_id}: inside the dataset {parent}", hint="choose a name outside other datasets"
            )
    if final.is_symlink() or (final.exists() and not final.is_dir()):
        raise BadInput(f"--minari {dataset_id}: {final} is not a folder", hint="remove it or choose another name")
    if final.exists():
        if not force:
            raise OutputExists(
                f"--minari {dataset_id}: {final} exists", final, hint="pass --force to replace it, or another name"
            )
        nested = [m for m in final.rglob("metadata.json") if m.parent != final / "data"]
        if nested:
            raise BadInput(
                f"--minari {dataset_id}: {final} holds other datasets ({nested[0].parent.parent.relative_to(root)})",
                hint="--force replaces one dataset, never others inside it",
            )


def _write_dataset(final, root, dataset_id, episodes, env_spec, expert, obs_space, act_space, description) -> Path:
    """Minari writes the dataset into a temporary root beside ``root``'s datasets; it is then renamed into place."""
    minari = _minari()
    tmp_root = Path(tempfile.mkdtemp(prefix=".cdrb-export-", dir=root))
    old = os.environ.get("MINARI_DATASETS_PATH")
    try:
        os.environ["MINARI_DATASETS_PATH"] = str(tmp_root)
        # Minari makes the environment to read it; a gymnasium-robotics maze then writes its XML into the temp
        # folder and leaves it there: here that folder is one of the export's own, removed below
        (tmp_root / ".tmp").mkdir()
        with temp_folder_at(tmp_root / ".tmp"), warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # Minari's advice about authors, permalinks and eval envs
            minari.create_dataset_from_buffers(
                dataset_id,
                episodes,
                env=env_spec,
                algorithm_name=f"cdrb {expert.kind}",
                observation_space=obs_space,
                action_space=act_space,
                description=description,
                data_format="hdf5",
            )
        replace_folder(tmp_root / dataset_id, final)  # final.parent: made by the caller
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old
        shutil.rmtree(tmp_root, ignore_errors=True)
    return final
