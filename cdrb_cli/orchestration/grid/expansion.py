"""The stage graph of a grid: its tasks (one `cdrb` command and the artifact it writes each) in dependency
order."""

from __future__ import annotations

import os
from pathlib import Path

from cdrb_cli.orchestration.grid.commands import input_files
from cdrb_cli.orchestration.grid.flags import nested, without_setting
from cdrb_cli.orchestration.grid.reuse import buffer_task, reuse_finished, train_snapshot
from cdrb_cli.orchestration.grid.spec import GridSpec, Task, Variant

# ------------------------------------------------------------------------------------------------ the stage graph


BASE = Variant.model_construct(
    name="", methods=None, envs=None, cluster=[], train=[], eval=[], stream=None, eval_settings=True
)


def collect_flags_for(spec: GridSpec, env: str) -> list[str]:
    """The extra `cdrb collect` flags of ``env``'s demos: those of every settings entry that applies to it."""
    return [f for s in spec.settings if s.env in (None, env) for f in s.collect]


def model_variants(spec: GridSpec, env: str, method: str) -> list[Variant]:
    """The variants whose models ``method`` trains on ``env``: the base, then each variant with its own models."""
    return [BASE, *(v for v in spec.variants if v.own_model and v.applies(env, method))]


def cluster_flags_for(spec: GridSpec, env: str, method: str, variant: Variant = BASE) -> list[str]:
    """The extra `cdrb cluster` flags of the buffer ``method`` trains with on ``env`` in ``variant``: the settings'
    that apply, then the variant's."""
    return [f for s in spec.settings if s.env in (None, env) and s.method in (None, method) for f in s.cluster] + list(
        variant.cluster
    )


def flags_for(spec: GridSpec, env: str, method: str, variant: Variant = BASE) -> tuple[list[str], list[str]]:
    """The extra `cdrb train` and `cdrb eval` flags of ``method`` on ``env`` in ``variant``: the settings that
    apply, in order (included files first), then the variant's own."""
    train, evaluate = [], []
    for s in spec.settings:
        if s.env in (None, env) and s.method in (None, method):
            train += s.train
            evaluate += s.eval
    return (
        without_repeated_sets(train + variant.train),
        without_repeated_sets((evaluate if variant.eval_settings else []) + variant.eval),
    )


def without_repeated_sets(flags: list[str]) -> list[str]:
    """``flags`` less every ``--set KEY=VALUE`` that gives KEY the value it already has there (a settings file
    included beside another that states the same setting): the command means the same and reads once. A repeat
    that restores a value overridden in between (the key itself, or one above or inside it) is kept."""
    out, value = [], {}
    i = 0
    while i < len(flags):
        f = flags[i]
        if f == "--set" and i + 1 < len(flags):
            pair, width = flags[i + 1], 2
        elif f.startswith("--set="):
            pair, width = f.removeprefix("--set="), 1
        else:
            out.append(f)
            i += 1
            continue
        key, eq, val = pair.partition("=")
        key = key.strip()
        if not (eq and value.get(key) == val):
            out += flags[i : i + width]
            for other in [k for k in value if nested(k, key)]:  # a setting above or inside it changed too
                del value[other]
            if eq:
                value[key] = val
        i += width
    return out


#: in an eval flag's value, the path of the environment's buffer (the base clustering): a planner that keeps no
#: buffer names it as its route buffer, e.g. ``eval = { avoid = { route_buffer = "{buffer}" } }``
BUFFER_PLACEHOLDER = "{buffer}"


def expand(spec: GridSpec) -> list[Task]:
    """The grid's tasks in an order where every task comes after the tasks it reads from."""
    from cdrb_cli.methods.registry import METHODS

    out, tasks, trains = spec.out, [], set()
    variants = spec.variants or [BASE]
    evals: dict[str, list[tuple[str, Path]]] = {v.name: [] for v in variants}
    for env in spec.envs:
        folder = out / env
        demos = folder / "demos.h5"
        collect_id = f"collect {env}"
        collect_extra = collect_flags_for(spec, env)
        tasks.append(
            Task(
                collect_id,
                "collect",
                ["collect", env, "-n", str(spec.demos_of(env)), "--seed", str(spec.data_seed), *collect_extra]
                + ["--out", str(demos)],
                [demos],
            )
        )
        buffers: dict[str, tuple[str, Path]] = {}  # cluster flags (JSON) -> (task id, buffer path)

        for method in spec.methods:
            needs_buffer = METHODS.get(method).needs_buffer
            for v in variants:
                if not v.applies(env, method):
                    continue
                own_model = v.own_model
                model_v = v if own_model else BASE  # whose training flags and buffer the models have
                if needs_buffer:
                    flags = cluster_flags_for(spec, env, method, model_v)
                    vcluster, vbuffer = buffer_task(spec, env, flags, buffers, tasks)
                deps = [collect_id] + ([vcluster] if needs_buffer else [])
                inputs = [demos] + ([vbuffer] if needs_buffer else [])
                mfolder = folder / v.name if own_model else folder
                efolder = folder / v.name if v.name else folder
                vtag = f"{v.name}/" if own_model else ""
                train_extra, eval_extra = flags_for(spec, env, method, model_v)[0], flags_for(spec, env, method, v)[1]
                eval_extra, read_ids, read_files = _placeholders(spec, env, method, eval_extra, buffers, tasks)
                length, snaps = spec.curve(env, method, model_v.name)
                for seed in spec.seeds:
                    model = mfolder / f"{method}-s{seed}.h5"
                    train_id = f"train {env}/{vtag}{method}-s{seed}"
                    if train_id not in trains:
                        trains.add(train_id)
                        argv = ["train", str(demos), "--method", method, "--preset", spec.preset, "--seed", str(seed)]
                        argv += ["--buffer", str(vbuffer)] if needs_buffer else []
                        argv += without_setting(train_extra, "train", "steps") if length else train_extra
                        argv += ["--steps", str(length)] if length else []
                        if snaps:
                            argv += ["--snapshot-at", ",".join(map(str, snaps))]
                        if spec.tensorboard:
                            argv += ["--log-dir", str(spec.out / "tensorboard" / env / f"{vtag}{method}-s{seed}")]
                        argv += ["--out", str(model), "--device", spec.device]
                        outputs = [model] + [train_snapshot(model, s) for s in snaps]
                        tasks.append(Task(train_id, "train", argv, outputs, deps, inputs))
                    points = [(s, train_snapshot(model, s)) for s in snaps] + [(length, model)]
                    stream = v.stream or spec.eval_stream
                    seeds = spec.eval_seeds if spec.eval_seeds is not None else [seed + spec.eval_seed_offset]
                    for steps, m in points:
                        at = f".step{steps}" if m != model else ""
                        tag = f"{env}/{v.name + '/' if v.name else ''}{method}-s{seed}{at}"
                        ev = efolder / f"eval-{method}-s{seed}{at}.h5"
                        argv = ["eval", str(m), "--stream", stream, "--seeds", ",".join(map(str, seeds))]
                        argv += ["--episodes", str(spec.eval_episodes), *eval_extra]
                        argv += ["--out", str(ev), "--device", spec.device]
                        meta = {"env": env, "method": method, "variant": v.name, "seed": seed, "steps": steps}
                        if spec.tensorboard:  # the eval's figures join its model's training curves
                            meta["log_dir"] = str(spec.out / "tensorboard" / env / f"{vtag}{method}-s{seed}")
                        tasks.append(
                            Task(
                                f"eval {tag}",
                                "eval",
                                argv,
                                [ev],
                                [train_id, *read_ids],
                                [m, *read_files],
                                meta | {"stream": stream},
                            )
                        )
                        if m == model:
                            evals[v.name].append((f"eval {tag}", ev))
    _link_flag_files(tasks)
    if spec.reuse:
        tasks = reuse_finished(spec, tasks)
    return tasks + (_reports(out, evals) if spec.report else [])


def _reports(out: Path, evals: dict[str, list[tuple[str, Path]]]) -> list[Task]:
    """One `cdrb report` task per variant over its final models' evals (``evals``: variant name -> (task id, eval
    file) pairs)."""
    tasks = []
    for name, items in evals.items():
        if not items:
            continue
        report = out / ("report.md" if not name else f"report-{name}.md")
        argv = ["report", *[str(p) for _, p in items], "--out", str(report)]
        tasks.append(
            Task(
                "report" if not name else f"report {name}",
                "report",
                argv,
                [report],
                [i for i, _ in items],
                [p for _, p in items],
            )
        )
    return tasks


def _placeholders(spec: GridSpec, env: str, method: str, flags: list[str], buffers: dict, tasks: list[Task]):
    """(``flags`` with :data:`BUFFER_PLACEHOLDER` as the environment's buffer, the task ids and files that adds to
    what the eval reads): the buffer's clustering is added to ``tasks`` when none made it yet."""
    if not any(BUFFER_PLACEHOLDER in f for f in flags):
        return flags, [], []
    cluster_id, env_buffer = buffer_task(spec, env, cluster_flags_for(spec, env, method), buffers, tasks)
    return [f.replace(BUFFER_PLACEHOLDER, str(env_buffer)) for f in flags], [cluster_id], [env_buffer]


def flag_files(argv: list[str]) -> list[Path]:
    """The files a command line's options name for the command to read (``--flag FILE`` or ``--flag=FILE``)."""
    return input_files(argv[1:], argv[0])


def _link_flag_files(tasks: list[Task]) -> None:
    """Every file a task's flags name becomes one of its inputs (its memo then hashes it, so editing a map re-runs
    the evals that read it), and a task that writes such a file becomes one of its dependencies."""
    writer = {Path(os.path.normpath(p)): t.id for t in tasks for p in t.outputs}
    for t in tasks:
        for f in (Path(os.path.normpath(f)) for f in flag_files(t.argv)):
            if f not in t.inputs:
                t.inputs.append(f)
            if f in writer and writer[f] not in t.deps and writer[f] != t.id:
                t.deps.append(writer[f])
