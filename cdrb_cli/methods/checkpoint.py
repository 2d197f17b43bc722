"""Checkpoint I/O for any method: its modules, their EMA copies, its optimizers, the normalizer, the training
curve, and what the method needs for sampling (``extra_arrays``) — as plain numeric datasets of the model artifact,
never pickles. Layout (docs/format.md):

* ``weights/<module>/<tensor>`` and ``ema/<module>/<tensor>``: ``state_dict()`` of each module and its average;
* ``optim/<optimizer>/<module>/<parameter>/<state>``: every tensor of each parameter's optimizer state (Adam:
  ``exp_avg``, ``exp_avg_sq``, ``step``), by parameter name, so the layout does not depend on parameter order;
* ``normalizer/low|high``, ``curve/step|loss`` (and ``curve/valid_step|valid_loss``).

:func:`load_method` is the inference loader (plan, eval, benchmarks); :func:`restore` continues training.
"""

from __future__ import annotations

import copy

import numpy as np

from cdrb_cli.buffer import Normalizer
from cdrb_cli.errors import BadInput, OutputExists
from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Method, build_method


def _param_names(method: Method, optimizers: dict) -> dict[int, str]:
    """``<module>/<parameter>`` of every parameter an optimizer updates (each must live in one of the method's
    modules: that is where the checkpoint keeps it)."""
    names = {id(p): f"{m}/{n}" for m, module in method.modules().items() for n, p in module.named_parameters()}
    for o, opt in optimizers.items():
        for group in opt.param_groups:
            if any(id(p) not in names for p in group["params"]):
                raise ValueError(
                    f"{method.name}: optimizer {o!r} updates a parameter outside modules(); put it in a module "
                    "(e.g. an nn.ParameterDict) so the checkpoint keeps it"
                )
    return names


def checkpoint_arrays(method: Method, ema: dict, optimizers: dict, curve: list) -> dict[str, np.ndarray]:
    """Every array of a model artifact for the training state (method, EMA modules, optimizers, curve)."""
    arrays: dict[str, np.ndarray] = {}
    for m, module in method.modules().items():
        for name, t in module.state_dict().items():
            arrays[f"weights/{m}/{name}"] = t.detach().cpu().numpy()
    for m, module in ema.items():
        for name, t in module.state_dict().items():
            arrays[f"ema/{m}/{name}"] = t.detach().cpu().numpy()
    names = _param_names(method, optimizers)
    for o, opt in optimizers.items():
        for group in opt.param_groups:
            for p in group["params"]:
                for key, value in opt.state.get(p, {}).items():
                    if torch.is_tensor(value):
                        arrays[f"optim/{o}/{names[id(p)]}/{key}"] = value.detach().cpu().numpy()
    arrays["normalizer/low"] = method.normalizer.low.astype(np.float32)
    arrays["normalizer/high"] = method.normalizer.high.astype(np.float32)
    arrays["curve/step"] = np.array([c[0] for c in curve], dtype=np.int64)
    arrays["curve/loss"] = np.array([c[1] for c in curve], dtype=np.float64)
    checked = [c for c in curve if c[2] is not None]
    if checked:
        arrays["curve/valid_step"] = np.array([c[0] for c in checked], dtype=np.int64)
        arrays["curve/valid_loss"] = np.array([c[2] for c in checked], dtype=np.float64)
    arrays.update(method.extra_arrays())
    return arrays


def _load_module(module, tensors: dict[str, np.ndarray], where: str) -> None:
    state = {k: torch.from_numpy(np.array(v)) for k, v in tensors.items()}
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[1:2] or str(exc).splitlines()[:1]
        raise BadInput(
            f"{where}: weights do not fit the network in its config: {first[0].strip()}",
            hint="re-train the model (or pass the artifact its config belongs to)",
        ) from None


def load_weights(model, method: Method, prefix: str = "weights", modules=None) -> None:
    """Load ``prefix/<module>/...`` of a model artifact into the method's modules (or into ``modules``)."""
    targets = method.modules() if modules is None else modules
    for m, module in targets.items():
        tensors = model.tensors(f"{prefix}/{m}")
        if not tensors:
            raise BadInput(f"{model.path}: no /{prefix}/{m} tensors for module {m!r}", hint="re-train the model")
        _load_module(module, tensors, str(model.path))


def make_ema(method: Method) -> dict:
    """Frozen copies of the modules the method averages."""
    mods = method.modules()
    return {m: copy.deepcopy(mods[m]).requires_grad_(False) for m in method.ema_modules()}


def restore(model, method: Method, ema: dict, optimizers: dict, device) -> tuple[int, list, float]:
    """Load a checkpoint into a freshly built method, its EMA modules and optimizers; returns (step, curve, wall
    time so far)."""
    load_weights(model, method, "weights")
    load_weights(model, method, "ema", ema)
    names = _param_names(method, optimizers)
    for o, opt in optimizers.items():
        tensors = model.tensors(f"optim/{o}")
        sd = opt.state_dict()
        state, used = {}, 0
        index = 0
        for group in opt.param_groups:
            for p in group["params"]:
                prefix = names[id(p)] + "/"
                entry = {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
                for k, v in entry.items():  # per-parameter tensors (Adam's moments) or scalars (its step)
                    if np.shape(v) not in ((), tuple(p.shape)):
                        raise OutputExists(
                            f"{model.path}: optimizer tensor /optim/{o}/{prefix}{k} has shape {np.shape(v)}, but its "
                            f"parameter has {tuple(p.shape)}",
                            model.path,
                            hint="the checkpoint is damaged: train again with --force",
                        )
                if entry:  # a parameter that never had a gradient has no state
                    state[index] = {k: torch.from_numpy(np.array(v)).to(device) for k, v in entry.items()}
                    if "step" in state[index]:  # optimizers keep their step count on the CPU
                        state[index]["step"] = state[index]["step"].cpu()
                    used += len(entry)
                index += 1
        if used != len(tensors):  # a stored tensor no parameter of this method claims
            raise OutputExists(
                f"{model.path}: the state of optimizer {o!r} does not fit the method's parameters",
                model.path,
                hint="train again with --force",
            )
        sd["state"] = state
        opt.load_state_dict(sd)
    steps = model.arrays["curve/step"].tolist()
    losses = model.arrays["curve/loss"].tolist()
    checked = dict(
        zip(
            model.arrays.get("curve/valid_step", np.zeros(0)).tolist(),
            model.arrays.get("curve/valid_loss", np.zeros(0)).tolist(),
        )
    )
    curve = [(s_, l_, checked.get(s_)) for s_, l_ in zip(steps, losses)]
    return model.manifest.state.step, curve, model.manifest.state.wall_time_s


def normalizer_of(model) -> Normalizer:
    return Normalizer(low=model.arrays["normalizer/low"], high=model.arrays["normalizer/high"])


def check_tensors(model, method_cls_args, buffer_graph=None) -> None:
    """The model's config against its stored tensors, before anything is allocated: the method is built on
    PyTorch's meta device (shapes only, no memory) and every module's state_dict must match ``weights/`` and
    ``ema/`` exactly, so a config whose sizes were tampered with (``net.dim`` 40,000) is refused with the tensor
    it does not fit, instead of allocating gigabytes."""
    with torch.device("meta"):
        probe = build_method(*method_cls_args, device="meta", buffer_graph=buffer_graph)
    expected: dict[str, tuple[int, ...]] = {}
    for m, module in probe.modules().items():
        for name, t in module.state_dict().items():
            expected[f"weights/{m}/{name}"] = tuple(t.shape)
            if m in probe.ema_modules():
                expected[f"ema/{m}/{name}"] = tuple(t.shape)
    stored = {k: tuple(v.shape) for k, v in model.arrays.items() if k.startswith(("weights/", "ema/"))}
    for key in sorted(set(expected) | set(stored)):
        if expected.get(key) != stored.get(key):
            what = (
                f"has no tensor /{key}"
                if key not in stored
                else f"tensor /{key} has shape {stored[key]}, but its config builds {expected[key]}"
                if key in expected
                else f"tensor /{key} belongs to no module of its config"
            )
            raise BadInput(f"{model.path}: {what}", hint="the weights do not fit the config: re-train the model")


def load_method(model, device="cpu", ema: bool = True) -> Method:
    """Rebuild the method of a model artifact, ready to sample: its modules hold the EMA weights (``ema``) or the
    raw ones, in eval mode."""
    from cdrb_cli.methods.registry import METHODS

    cfg, spec = model.manifest.config, model.manifest.env
    entry = METHODS.get(cfg.method.name)
    points = model.arrays.get("buffer/points")
    if entry.needs_buffer and points is None:
        raise BadInput(f"{model.path}: {entry.name} model without /buffer/points", hint="re-train it")
    args = (cfg, spec, normalizer_of(model), points)
    graph = None
    if "buffer/graph/edges" in model.arrays:  # balls measured along the buffer's transition graph
        graph = (model.arrays["buffer/graph/edges"], model.arrays["buffer/graph/weights"])
    elif getattr(cfg.method, "ball", "euclidean") == "geodesic":
        raise BadInput(f"{model.path}: a model with geodesic balls without /buffer/graph", hint="re-train it")
    check_tensors(model, args, graph)
    method = build_method(*args, device=device, buffer_graph=graph)
    if ema:
        mods = method.modules()
        load_weights(model, method, "ema", {m: mods[m] for m in method.ema_modules()})
        rest = {m: mod for m, mod in mods.items() if m not in method.ema_modules()}
        if rest:
            load_weights(model, method, "weights", rest)
    else:
        load_weights(model, method, "weights")
    return method.eval()
