"""The Python API (cdrb_cli.api): plans and evaluations with typed results, the same as the CLI's."""

from __future__ import annotations

import itertools
import os
import re
from pathlib import Path

import numpy as np
import pytest

from cdrb_cli import api, artifacts
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.config import train_config
from cdrb_cli.stages.train import train


@pytest.fixture(scope="module")
def model(small_data, tmp_path_factory):
    demos, buffer = small_data
    cfg = train_config(demos, buffer, "cdrb", {"steps": 20, "net.dim": 8, "checkpoint_every": 20})
    return train(demos, buffer, cfg, tmp_path_factory.mktemp("api") / "m.h5")


def test_plan_from_coordinates_holds_start_and_goal_and_measures_obstacles(model, monkeypatch):
    from cdrb_cli import torch_utils

    tuned = []
    monkeypatch.setattr(torch_utils, "keep_freed_memory", lambda: tuned.append(1))
    planner = api.Planner(model.path)
    assert not tuned, "the API changed its caller's allocator"
    plans = planner.plan(start=[0.0, 0.0], goal=[6.0, 6.0], n=4, seed=3)
    H, D = planner.method.horizon, planner.spec.obs_dim
    assert plans.states.shape == (4, H, D) and plans.pair_index.tolist() == [0, 0, 0, 0]
    np.testing.assert_array_equal(plans.states[:, 0, :2], np.zeros((4, 2)))
    np.testing.assert_array_equal(plans.states[:, -1, :2], np.full((4, 2), 6.0))
    assert plans.in_obstacle.shape == (4,) and plans.through_obstacle.dtype == bool
    again = planner.plan(start=[0.0, 0.0], goal=[6.0, 6.0], n=4, seed=3)
    np.testing.assert_array_equal(plans.states, again.states)  # deterministic given the seed
    with pytest.raises(BadInput):
        planner.plan(start=[0.0, 0.0, 0.0], goal=[6.0, 6.0])


def test_evaluate_writes_the_eval_artifact_and_returns_its_summary(model, tmp_path):
    summary = api.evaluate(model.path, tmp_path / "e.h5", episodes=2, seeds=[0], stream="tune")
    ev = artifacts.load(tmp_path / "e.h5", "eval")
    assert summary == ev.manifest.summary and summary.per_seed[0].episodes == 2
    assert summary.weighted_success_mean is not None
    # the CLI's rule: the same eval again is up to date (not redone); another one never over it without force
    before = (tmp_path / "e.h5").stat().st_mtime_ns
    again = api.evaluate(model.path, tmp_path / "e.h5", episodes=2, seeds=[0], stream="tune")
    assert again == summary and (tmp_path / "e.h5").stat().st_mtime_ns == before
    with pytest.raises(BadInput, match="not made by this exact command") as err:
        api.evaluate(model.path, tmp_path / "e.h5", episodes=3, seeds=[0], stream="tune")
    assert "force=True" in err.value.line() and "--" not in err.value.line()  # the argument, not the CLI's flag
    redone = api.evaluate(model.path, tmp_path / "e.h5", episodes=3, seeds=[0], stream="tune", force=True)
    assert redone.per_seed[0].episodes == 3


@pytest.mark.parametrize(
    "kw, needle",
    [
        (dict(start="abc"), "not a list of numbers"),
        (dict(start=[[0.0, 0.0]]), "a flat list of numbers"),
        (dict(start=np.array([1j, 0])), "start: complex numbers"),  # a cast would drop the imaginary part
        (dict(start=[True, False]), "start: booleans"),  # or read True as 1.0
        (dict(start=[float("nan"), 0.0]), "start = [nan, 0.0]: not finite"),
        (dict(steps=-3), "^steps=-3: "),
        (dict(steps=0), "^steps=0: "),
        (dict(n=2.5), "n=2.5"),
        (dict(n=True), "n=True"),
        (dict(n=10**6), "n=1000000"),
        (dict(seed=-1), "seed"),
        (dict(seed=2**70), "seed"),
        (dict(sampler="nope"), "sampler='nope'"),
    ],
)
def test_plan_arguments_are_checked_as_the_cli_checks_them(model, kw, needle):
    """One typed, one-line error per bad argument (never numpy's, never a silent wrap or truncation); a needle
    starting with ^ is how the line starts (the argument's name, not the setting's key it becomes)."""
    planner = api.Planner(model.path)
    args = dict(start=[0.0, 0.0], goal=[6.0, 6.0]) | kw
    with pytest.raises(BadInput) as err:
        planner.plan(**args)
    line = err.value.line()
    assert (line.startswith(needle[1:]) if needle[0] == "^" else needle in line) and "\n" not in line, line


def test_an_unfinished_model_is_refused_unless_allowed_and_its_eval_says_its_step(small_data, model, tmp_path):
    """As `cdrb plan`/`cdrb eval` without --allow-partial: a training's checkpoint is refused by name; allowed, it
    plans with a warning, and its eval records the step the training stopped at (not the steps it was set for, which
    `cdrb select` would read as a finished model's)."""
    demos, buffer = small_data
    six = train(demos, buffer, train_config(demos, buffer, "cdrb", {"steps": 6, "net.dim": 8}), tmp_path / "six.h5")
    m = six.manifest  # six steps of a training set for 20, as a checkpoint of it reads
    update = {
        "state": m.state.model_copy(update={"finished": False}),
        "config": m.config.model_copy(update={"steps": 20}),
    }
    part = artifacts.save(tmp_path / "part.h5", "model", m.model_copy(update=update), six.arrays)
    with pytest.raises(BadInput, match="stopped at step 6 of 20.*allow_partial=True"):
        api.Planner(part)
    with pytest.raises(BadInput, match="stopped at step 6 of 20"):
        api.evaluate(part, tmp_path / "e.h5", episodes=1, seeds=[0], stream="tune")
    assert not (tmp_path / "e.h5").exists()
    assert api.Planner(part, allow_partial=True).plan([0.0, 0.0], [6.0, 6.0]).states.shape[0] == 1
    summary = api.evaluate(part, tmp_path / "e.h5", episodes=1, seeds=[0], stream="tune", allow_partial=True)
    assert summary.model_steps == 6
    assert api.evaluate(model.path, tmp_path / "f.h5", episodes=1, seeds=[0], stream="tune").model_steps == 20


def test_numpy_numbers_are_numbers_and_other_arguments_are_checked(model, tmp_path):
    """numpy integers (a seed from a numpy loop, an n from an array) plan as the Python ints they hold; a yes/no
    argument takes True or False only (a truthy "no" must not turn EMA weights on or overwrite a file); paths,
    devices, settings and seeds of the wrong type, a coordinate past float range, and a setting given both to the
    planner and to a call are one-line BadInputs."""
    planner = api.Planner(model.path)
    a = planner.plan([0.0, 0.0], [6.0, 6.0], n=np.int64(2), seed=np.int64(3))
    b = planner.plan([0.0, 0.0], [6.0, 6.0], n=2, seed=3)
    np.testing.assert_array_equal(a.states, b.states)
    ev = api.evaluate(model.path, tmp_path / "e.h5", episodes=np.int64(1), seeds=np.array([0]), seed=np.int64(1))
    assert ev.per_seed[0].episodes == 1
    bad = [
        (lambda: api.Planner(model.path, ema="no"), "ema = 'no': not True or False"),
        (lambda: api.Planner(model.path, allow_partial=1), "allow_partial"),
        (lambda: api.Planner(None), "model = None: not a path"),
        (lambda: api.Planner(model.path, device=None), "device = None"),
        (lambda: api.Planner(model.path, settings="avoid.best_of=4"), "settings = 'avoid.best_of=4': not a dict"),
        (lambda: planner.plan([0.0, 10**400], [6.0, 6.0]), "not a list of numbers"),
        (lambda: api.Planner(model.path, settings={"n": 3}).plan([0, 0], [6, 6], n=2), "n=2"),
        (lambda: api.evaluate(model.path, tmp_path / "e.h5", episodes=1, force="no"), "force = 'no'"),
        (lambda: api.evaluate(model.path, tmp_path / "g.h5", seeds=5), "seeds = 5: not a list of seeds"),
        (lambda: api.evaluate(model.path, None), "out = None: not a path"),
        # a dict's keys or a set's order would be run silently; None would silently mean the default stream
        (lambda: api.evaluate(model.path, tmp_path / "g.h5", seeds={0: 1}), "seeds = {0: 1}: not a list"),
        (lambda: api.evaluate(model.path, tmp_path / "g.h5", seeds={0, 1}), "seeds = {0, 1}: not a list"),
        (lambda: api.evaluate(model.path, tmp_path / "g.h5", seeds=np.array(0)), "seeds = array(0): not a list"),
        # one setting in two spellings, or twice in the dict, is given twice
        (
            lambda: api.evaluate(model.path, tmp_path / "g.h5", controller="pd", settings={"controller": "waypoint"}),
            "controller.name='pd' and settings controller='waypoint' (give it once)",
        ),
        (
            lambda: api.Planner(model.path, settings={"avoid.best_of": 2, "avoid.best-of": 3}),
            "settings avoid.best_of=2 and settings avoid.best-of=3",
        ),
        (lambda: api.Planner(model.path, settings={"batch": None}), "settings batch=None: null is not a batch size"),
        # a cast would read True as 1.0 and "1" as 1.0
        (lambda: planner.plan([True, 1.0], [6.0, 6.0]), "start: booleans, not real numbers"),
        (lambda: planner.plan([1.0, 1.0], ["6", "6"]), "goal: strings, not real numbers"),
        (lambda: planner.plan(np.array([0, 0], "datetime64[s]"), [6, 6]), "start: dates, not real numbers"),
        (lambda: planner.plan([np.timedelta64(1, "s"), 0.0], [6, 6]), "start: time spans, not real numbers"),
        (lambda: planner.plan(np.ma.masked_array([0.0, 9.0], [False, True]), [6, 6]), "start: masked values"),
        (lambda: planner.plan([None, 0.0], [6, 6]), "start: None where a number belongs"),
        (lambda: planner.plan([0.0] * 10**5, [6, 6]), "start: 100,000 numbers, more than the 4 of a"),
        (lambda: planner.plan([0.0, 0.0], __import__("torch").zeros(2, device="meta")), "goal: a tensor on the meta"),
        # the seed is an argument, not a setting: its error names it (not `cdrb config plan`)
        (lambda: planner.plan([0, 0], [6, 6], seed=-1), "seed = -1: not a seed"),
        (lambda: planner.plan([0, 0], [6, 6], steps=10**6), "steps=1000000: the model has T = "),
        (lambda: api.evaluate(model.path, tmp_path / "g.h5", seed=2**32), "seed = 4294967296: not a seed"),
        # a string where a number belongs is shown as the string it is
        (lambda: api.evaluate(model.path, tmp_path / "g.h5", settings={"avoid.best_of": "2"}), "best_of='2'"),
        # a value JSON has no form for is named with its setting
        (lambda: api.Planner(model.path, settings={"n": {1, 2}}), "settings n={1, 2}: a set is not a setting value"),
        (lambda: api.Planner(model.path, settings={"n": Path("3")}), "settings n=PosixPath('3'): a PosixPath is"),
        (lambda: api.Planner(model.path, settings={"n": object()}), ": an object is not a setting value"),
        # a list is refused for what it holds, not for being a list
        (lambda: api.Planner(model.path, settings={"n": [{1}]}), ": a set is not a setting value"),
    ]
    for call, needle in bad:
        with pytest.raises(BadInput) as err:
            call()
        assert needle in err.value.line() and "\n" not in err.value.line(), err.value.line()
    import torch

    # a tensor that takes part in autograd, or of a type numpy lacks (bfloat16), is its values, as a list of them is
    listed = planner.plan([0.0, 0.0], [6.0, 6.0], seed=1).features
    tensor = planner.plan(torch.tensor([0.0, 0.0], requires_grad=True), [6.0, 6.0], seed=1)
    np.testing.assert_array_equal(tensor.features, listed)
    half = planner.plan(torch.tensor([0.0, 0.0], dtype=torch.bfloat16), [6.0, 6.0], seed=1)
    np.testing.assert_array_equal(half.features, listed)
    # a setting given as a tensor is the number or list it holds, as a numpy one is
    from cdrb_cli.settings import from_mapping

    assert [s.value for s in from_mapping({"n": torch.tensor(3), "avoid.weights": torch.tensor([1.0, 2.0])})] == [
        3,
        [1.0, 2.0],
    ]

    class BytesPath:  # os.PathLike may return bytes
        def __fspath__(self):
            return os.fsencode(str(model.path))

    assert api.Planner(BytesPath()).plan([0.0, 0.0], [6.0, 6.0], seed=1).features.shape == listed.shape
    assert artifacts.load(tmp_path / "e.h5", "eval").manifest.summary.per_seed[0].episodes == 1  # not overwritten
    assert api.Planner(model.path, settings={"n": 3}).plan([0, 0], [6, 6]).states.shape[0] == 3
    # episodes, seeds and the stream left out are the CLI's defaults, so a settings dict may give them
    ev = api.evaluate(model.path, tmp_path / "s.h5", settings={"episodes": 1, "seeds": [3], "stream": "tune"})
    assert [(r.seed, r.episodes) for r in ev.per_seed] == [(3, 1)]
    assert artifacts.load(tmp_path / "s.h5", "eval").manifest.config.stream == "tune"


def test_a_planner_returns_the_iterates_it_is_asked_to_keep(model):
    """``keep_iterates`` (as `cdrb plan --set keep_iterates=N`) returns the intermediate iterates, in raw units,
    with their diffusion steps; keeping them changes no plan."""
    kept = api.Planner(model.path, settings={"keep_iterates": 3}).plan([0.0, 0.0], [6.0, 6.0], n=2, seed=1)
    plain = api.Planner(model.path).plan([0.0, 0.0], [6.0, 6.0], n=2, seed=1)
    np.testing.assert_array_equal(kept.features, plain.features)
    assert plain.iterates is None and plain.iterate_steps is None
    assert kept.iterates.shape == (2, 3, *kept.features.shape[1:]) and len(kept.iterate_steps) == 3
    assert kept.iterate_steps == sorted(kept.iterate_steps, reverse=True)  # from noisiest to cleanest
    np.testing.assert_allclose(
        kept.iterates[:, :, 0], np.repeat(kept.features[:, None, 0], 3, 1), atol=1e-5
    )  # pinned start, raw units


def test_a_planner_keeps_the_callers_torch_stream_and_refuses_steps_a_model_cannot_use(model, tiny_models):
    """Building a planner draws initial weights before loading the trained ones: the caller's global torch stream
    is kept as it was; denoising ``steps`` for a model that plans in one pass are refused, not ignored."""
    import torch

    torch.manual_seed(5)
    expected = torch.rand(4)
    torch.manual_seed(5)
    api.Planner(model.path)
    assert torch.equal(torch.rand(4), expected)
    mlp = api.Planner(tiny_models["mlp"].path)
    with pytest.raises(BadInput, match="plans in one pass"):
        mlp.plan([0.0, 0.0], [6.0, 6.0], steps=5)
    assert mlp.plan([0.0, 0.0], [6.0, 6.0]).states.shape[0] == 1


def test_the_onnx_runtime_plans_as_torch_does_to_rounding_and_repeats_exactly(model, tiny_models, monkeypatch):
    """runtime="onnx" runs the U-Net in ONNX Runtime from the first call: CDRB's and Diffuser's plans equal torch's
    to float rounding, the same seed gives the same plans; a model without a U-Net, a GPU, an unknown runtime and a
    missing onnxruntime are refused in one line."""
    import sys

    for m in (model, tiny_models["diffuser"]):
        reference = api.Planner(m.path, runtime="torch").plan([0.0, 0.0], [6.0, 6.0], n=8, seed=3)
        planner = api.Planner(m.path, runtime="onnx")
        first, again = (planner.plan([0.0, 0.0], [6.0, 6.0], n=8, seed=3) for _ in range(2))
        assert "_onnx" in planner.method.__dict__  # the session ran the network
        np.testing.assert_array_equal(first.features, again.features)
        np.testing.assert_allclose(first.features, reference.features, atol=1e-4)
        assert np.abs(first.features - reference.features).max() > 0 or m is model  # not torch under another name
    for kw, needle in (
        (
            {"runtime": "tensorrt"},
            "runtime = 'tensorrt': not a runtime (pass one of 'torch', 'onnx', 'compile', 'auto')",
        ),
        ({"runtime": None}, "runtime = None: not a string"),
    ):
        with pytest.raises(BadInput, match=re.escape(needle)):
            api.Planner(model.path, **kw)
    with pytest.raises(BadInput, match="runtime = 'onnx': is for the diffusion planners' temporal U-Net, and the mlp"):
        api.Planner(tiny_models["mlp"].path, runtime="onnx")
    from cdrb_cli.nets.runtime import check_runtime

    net = api.Planner(model.path).method.net
    with pytest.raises(BadInput, match=r"runs on the CPU, not cuda \(pass device='cpu'"):
        check_runtime("onnx", net, "cuda", "cdrb")
    # weights changed in place after the session was built: the next plan runs the new ones, as torch would
    import torch

    onnx_planner, torch_planner = api.Planner(model.path, runtime="onnx"), api.Planner(model.path, runtime="torch")
    onnx_planner.plan([0.0, 0.0], [6.0, 6.0], seed=1)
    for p in (onnx_planner, torch_planner):
        with torch.no_grad():
            for w in p.method.net.parameters():
                w.mul_(0.9)
    scaled = (p.plan([0.0, 0.0], [6.0, 6.0], n=4, seed=3).features for p in (onnx_planner, torch_planner))
    np.testing.assert_allclose(*scaled, atol=1e-4)
    # and between two repairs (a closed loop's re-plans), which look at the weights as plans do
    methods = onnx_planner.method, torch_planner.method
    start, goal = torch.full((2, methods[0].obs_dim), -0.5), torch.full((2, methods[0].obs_dim), 0.5)
    previous = methods[1].sample(start, goal, np.random.default_rng(0)).plans
    for m in methods:
        m.repair(start, goal, previous, 5, np.random.default_rng(1))
        with torch.no_grad():
            for w in m.net.parameters():
                w.mul_(0.9)
    repaired = (m.repair(start, goal, previous, 5, np.random.default_rng(2)).plans.numpy() for m in methods)
    np.testing.assert_allclose(*repaired, atol=1e-4)
    # and a network call outside any sampling call looks at the weights each time
    x, k = previous, torch.full((2,), 3)
    with torch.no_grad():
        for m in methods:
            m.sample_net(x, k)
            for w in m.net.parameters():
                w.mul_(0.5)
        direct = [m.sample_net(x, k).numpy() for m in methods]
    np.testing.assert_allclose(*direct, atol=1e-4)
    from cdrb_cli.nets.runtime import OnnxNet

    session = onnx_planner.method.__dict__["_onnx"][1]
    x, k = torch.zeros(1, *session.session.get_inputs()[0].shape[1:]), torch.zeros(1, dtype=torch.long)
    with pytest.raises(BadInput, match=re.escape("runs the network in float32, not torch.float64")):
        session(x.double(), k)
    # an exporter that fails (another torch version): one line, not its traceback
    monkeypatch.setattr(torch.onnx, "export", lambda *a, **kw: (_ for _ in ()).throw(TypeError("unexpected 'dynamo'")))
    with pytest.raises(BadInput, match=r"could not export and load the network: unexpected 'dynamo' \(leave runtime"):
        OnnxNet(onnx_planner.method.net, x, k)
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # as if it were not installed
    with pytest.raises(
        BadInput, match=re.escape("onnx and onnxruntime are not installed (pip install onnx onnxruntime)")
    ):
        api.Planner(model.path, runtime="onnx")


def test_the_auto_runtime_plans_small_batches_in_onnx_and_large_ones_in_torch(model, tiny_models, monkeypatch):
    """The API's default runtime "auto" runs a plan call whose first batch has up to AUTO_ONNX_BATCH rows in ONNX
    Runtime and a larger one in torch, the whole call in one runtime (its later batches and a route retry of some
    plans too), bit for bit as that runtime alone, and says which ran; weights written in place, even through
    ``.data``, are planned with; two threads planning with one planner get what each gets alone; where ONNX Runtime
    cannot run (no U-Net, not installed, an exporter that fails) it plans with torch instead of refusing."""
    import sys
    import threading

    import torch

    from cdrb_cli.nets.runtime import AUTO_ONNX_BATCH

    a, b = [0.0, 0.0], [6.0, 6.0]
    auto = api.Planner(model.path)
    explicit = {r: api.Planner(model.path, runtime=r) for r in ("onnx", "torch")}
    for n, runtime in ((1, "onnx"), (AUTO_ONNX_BATCH, "onnx"), (AUTO_ONNX_BATCH + 1, "torch")):
        plans = auto.plan(a, b, n=n, seed=5)
        assert plans.runtime == runtime, n
        same = explicit[runtime].plan(a, b, n=n, seed=5)
        assert same.runtime == runtime
        np.testing.assert_array_equal(plans.features, same.features)
    # the whole call in the first batch's runtime: a small last batch, and a buffer-route retry of a few plans
    for settings, n in (({"batch": AUTO_ONNX_BATCH + 2}, AUTO_ONNX_BATCH + 4), ({"avoid.fallback_route_k": 4}, 32)):
        plans = api.Planner(model.path, settings=settings).plan(a, b, n=n, seed=0)
        assert plans.runtime == "torch", settings
        torch_plans = api.Planner(model.path, runtime="torch", settings=settings).plan(a, b, n=n, seed=0)
        np.testing.assert_array_equal(plans.features, torch_plans.features)
    assert api.Planner(tiny_models["mlp"].path).plan(a, b, seed=0).runtime == "torch"
    # weights written through .data (which autograd's version counters miss) after the session was built
    before = auto.plan(a, b, n=1, seed=1).features
    with torch.no_grad():
        for planner in (auto, explicit["onnx"]):
            for w in planner.method.net.parameters():
                w.data.mul_(0.9)
    after = auto.plan(a, b, n=1, seed=1).features
    assert np.abs(after - before).max() > 1e-3
    np.testing.assert_array_equal(after, explicit["onnx"].plan(a, b, n=1, seed=1).features)
    # two threads on one planner: each call keeps its own runtime and plans
    shared = api.Planner(model.path)
    alone = {n: shared.plan(a, b, n=n, seed=2) for n in (1, AUTO_ONNX_BATCH + 4)}
    got: dict[int, list] = {1: [], AUTO_ONNX_BATCH + 4: []}

    def planning(n: int, times: int) -> None:
        for _ in range(times):
            got[n].append(shared.plan(a, b, n=n, seed=2))

    threads = [
        threading.Thread(target=planning, args=(1, 12)),
        threading.Thread(target=planning, args=(AUTO_ONNX_BATCH + 4, 3)),
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for n, results in got.items():
        assert results and all(r.runtime == alone[n].runtime for r in results), n
        for r in results:
            np.testing.assert_array_equal(r.features, alone[n].features)
    # an exporter that fails: one warning line naming the failure, and torch's plans
    warned: list[str] = []
    monkeypatch.setattr("cdrb_cli.ui.warn", warned.append)
    monkeypatch.setattr(torch.onnx, "export", lambda *a, **kw: (_ for _ in ()).throw(TypeError("unexpected 'dynamo'")))
    broken = api.Planner(model.path)
    fallback = broken.plan(a, b, n=1, seed=5)
    assert fallback.runtime == "torch" and broken.plan(a, b, n=1, seed=5).runtime == "torch"
    assert (
        len(warned) == 1
        and warned[0].startswith("runtime 'auto': this torch (")
        and warned[0].endswith("could not export and load the network: unexpected 'dynamo'; planning with torch")
    )
    np.testing.assert_array_equal(
        fallback.features, api.Planner(model.path, runtime="torch").plan(a, b, n=1, seed=5).features
    )
    monkeypatch.undo()
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # as if it were not installed
    assert api.Planner(model.path).plan(a, b, n=1, seed=5).runtime == "torch"


def test_the_compile_runtime_plans_as_torch_does_to_rounding_and_repeats_exactly(model, tiny_models, monkeypatch):
    """runtime="compile" runs the U-Net through torch.compile from the first call, whole: plans equal torch's to
    float rounding, the same seed and batch size give the same plans whatever was planned before, new weights are
    used at once; a model without a U-Net, a machine without a C++ compiler or Python's headers, and a compile that
    fails are refused in one line."""
    import importlib.util
    import shutil
    import sysconfig

    import torch
    from torch._dynamo.utils import counters

    from cdrb_cli.nets.runtime import check_runtime

    reference = api.Planner(model.path, runtime="torch").plan([0.0, 0.0], [6.0, 6.0], n=8, seed=3)
    graphs = counters["stats"]["unique_graphs"]
    planner = api.Planner(model.path, runtime="compile")
    first = planner.plan([0.0, 0.0], [6.0, 6.0], n=8, seed=3)
    assert counters["stats"]["unique_graphs"] > graphs  # dynamo compiled a graph (fullgraph: the whole network)
    planner.plan([0.0, 0.0], [6.0, 6.0], n=4, seed=3)  # another batch size: its own graph, the first one kept
    np.testing.assert_array_equal(planner.plan([0.0, 0.0], [6.0, 6.0], n=8, seed=3).features, first.features)
    np.testing.assert_allclose(first.features, reference.features, atol=1e-4)
    x, k = torch.as_tensor(first.features, dtype=torch.float32), torch.full((8,), 3)  # the plans' batch: no recompile
    with torch.inference_mode():
        before = planner.method.sample_net(x, k)
        for w in planner.method.net.parameters():
            w.mul_(0.5)
        after, eager = planner.method.sample_net(x, k), planner.method.net(x, k)
    assert (before - after).abs().max() > 1e-3  # the new weights ran, as torch runs them
    np.testing.assert_allclose(after.numpy(), eager.numpy(), atol=1e-4)
    with pytest.raises(BadInput, match="'compile': is for the diffusion planners' temporal U-Net, and the mlp method"):
        api.Planner(tiny_models["mlp"].path, runtime="compile")
    # a compile that fails at the first plan: one line naming the runtime
    failing = lambda *a, **kw: (_ for _ in ()).throw(torch._dynamo.exc.TorchDynamoException("no working compiler\nx"))
    from cdrb_cli.nets.runtime import CompiledNet

    broken = api.Planner(model.path, runtime="compile")
    wrapped = CompiledNet(broken.method.net)
    wrapped.module = failing  # as torch.compile's module would raise it
    broken.method._compiled = (broken.method.net, wrapped)
    with pytest.raises(BadInput, match=re.escape("could not compile the network: no working compiler (leave runtime")):
        broken.plan([0.0, 0.0], [6.0, 6.0])
    net = planner.method.net
    from torch._inductor import config

    monkeypatch.setattr(config.cpp, "cxx", (None, "g++"))  # what Inductor calls without $CXX
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(BadInput, match=re.escape("runtime = 'compile': no C++ compiler 'g++' on the PATH")):
        check_runtime("compile", net, "cpu", "cdrb")
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(BadInput, match=re.escape("runtime = 'compile': Triton is not installed (install the Triton")):
        check_runtime("compile", net, "cuda", "cdrb")
    monkeypatch.setattr(sysconfig, "get_path", lambda name, *a, **kw: "/nonexistent")
    with pytest.raises(BadInput, match=re.escape("Python's C headers (Python.h) are not installed")):
        check_runtime("compile", net, "cpu", "cdrb")


def test_points_read_as_the_cli_reads_them_and_errors_name_the_argument(model):
    """The API's start and goal take the CLI's forms (Fetch: a start as the block's x,y) and its errors name the
    Python argument (``start``), not the CLI's flag."""
    from cdrb_cli.envs.registry import family_of, make_spec

    spec = make_spec("fetch-push-obstacle")
    fam = family_of(spec)
    block = fam.parse_point(spec, "1.25,0.65", "start")
    np.testing.assert_array_equal(block, fam.parse_point(spec, "1.25,0.65", "--start"))
    assert block.shape == (spec.obs_dim,) and block[3] == 1.25  # the block's x, the gripper at home
    maze = make_spec("maze")
    for text in ("1.25,0.65,,", ",1.25,0.65", "1.25,,0.65"):  # a number left out is not a separator to skip
        for s in (spec, maze):
            with pytest.raises(BadInput, match="an empty value between commas"):
                family_of(s).parse_point(s, text, "--start")
    with pytest.raises(BadInput, match="not a list of numbers"):  # a space inside a number is a typo, not 1.5
        family_of(maze).parse_point(maze, "1 .5,0", "--start")
    # one trailing comma is how a list is often written, as --seeds takes it
    np.testing.assert_array_equal(fam.parse_point(spec, "1.25,0.65,", "start"), block)
    # a full state: the state a reset gives is taken; one with a velocity no arm reaches (a typo) is refused
    full = ",".join(repr(float(v)) for v in block)
    np.testing.assert_array_equal(fam.parse_point(spec, full, "--start"), block)
    fast = block.copy()
    fast[spec.state_labels.index("grip_vx")] = 9999.0
    with pytest.raises(BadInput, match="grip_vx = 9999: a velocity beyond"):
        fam.parse_point(spec, ",".join(map(str, fast)), "--start")
    reach = make_spec("fetch-reach")
    at_rest = family_of(reach).parse_point(reach, "1.3,0.75,0.5", "--goal")
    fast = at_rest.copy()
    fast[reach.state_labels.index("finger_vl")] = -3.0
    with pytest.raises(BadInput, match="finger_vl = -3: a velocity beyond"):
        family_of(reach).parse_point(reach, ",".join(map(str, fast)), "--start")
    with pytest.raises(BadInput) as err:
        api.Planner(model.path).plan([0.0, 10.0], [6.0, 6.0])
    assert err.value.line().startswith("start ") and "--start" not in err.value.line()


def test_api_errors_name_python_arguments_where_the_cli_names_flags(model, tmp_path, monkeypatch):
    """The device, the scene file and the output are named as the caller gave them (``device='cuda'``, ``scene``),
    with the fix in the same dialect; the CLI's messages keep their flags."""
    import torch

    from cdrb_cli.torch_utils import setup_torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(BadInput) as err:
        api.Planner(model.path, device="cuda")
    assert err.value.line() == "device='cuda': no CUDA device is available (use device='cpu')"
    with pytest.raises(BadInput, match="--device cuda: no CUDA device is available \\(use --device cpu\\)"):
        setup_torch("cuda", allocator=False)
    with pytest.raises(BadInput) as err:
        api.Planner(model.path, scene=tmp_path / "missing.txt")
    assert err.value.line().startswith("scene ") and "--" not in err.value.line()
    (tmp_path / "taken.h5").write_bytes(b"not an eval")
    with pytest.raises(BadInput) as err:
        api.evaluate(model.path, tmp_path / "taken.h5", episodes=1, seeds=[0], stream="tune")
    assert err.value.line().startswith("out ") and "force=True" in err.value.line()


@pytest.mark.parametrize(
    "call, needle",
    [
        (lambda m: api.Planner(m, settings={"seed": 5}), "pass seed=N"),
        (lambda m: api.Planner(m, settings={"scene": "x.txt"}), "pass scene=FILE"),
        (lambda m: api.Planner(m, settings={"n=3": 2}), '{"avoid.best_of": 4}'),
        (lambda m: api.Planner(m).state([0.0, 0.0], None), 'pass "start" or "goal"'),
        (lambda m: api.evaluate(m, "/tmp/x.h5", seeds=[0, 0]), "repeated seeds"),
        (lambda m: api.evaluate(m, "", episodes=1), "out = '': an empty path"),  # Path("") is the working folder
        (lambda m: api.evaluate(m, "/tmp/x.h5", seeds=itertools.count()), "at most 1000 items"),
        (lambda m: api.evaluate(m, "/tmp/x.h5", protocol="detour"), "walls added: scene=FILE)"),
        (lambda m: api.evaluate(m, "/tmp/x.h5", replan=5), "replan=5: not never, every:N or deviation:D"),
        (lambda m: api.Planner("/tmp/" + "a" * 5000), "cannot be read (File name too long)"),
        (lambda m: api.evaluate("/tmp/" + "a" * 5000, "/tmp/x.h5", episodes=1), "cannot be read (File name too long)"),
    ],
)
def test_settings_that_are_arguments_and_unreadable_paths_are_named_in_python(model, call, needle):
    """A field given in ``settings`` that is a keyword argument, a key that is no dotted name, and a model path the
    file system cannot even look up: one BadInput each, in the API's words (no flag, no OSError)."""
    with pytest.raises(BadInput) as err:
        call(model.path)
    line = err.value.line()
    assert needle in line and "--" not in line and "Value error" not in line
