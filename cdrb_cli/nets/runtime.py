"""Where sampling's network calls run: torch (the default), ONNX Runtime on the CPU, torch's compiler, or ``auto``
(the Python API's default: ONNX Runtime for small batches on the CPU, torch otherwise).

At batch 1 a small temporal U-Net costs torch ~400 operator dispatches per pass, and that per-operation cost, not
arithmetic, is most of a plan's time on a CPU (a robot re-planning one plan at a time, the Python API).
ONNX Runtime runs the same network, exported once to memory, through its own CPU kernels at a fraction of that cost
per operation. It is the same network in another library's kernels: outputs agree with torch's to float rounding,
not bit for bit, and a ball sampler that meets a state on a ball's edge may then draw another buffer state, so the
runtime is a setting the caller chooses (``api.Planner(runtime="onnx")``). Within one runtime, plans are as
reproducible as torch's: the same seed gives the same plans.

``auto`` is a rule, not a guess: a sampling call (an API plan with its retries and repairs: ``runtime_scope``) runs
in ONNX Runtime when its first network call is on the CPU, in float32, at a batch of at most :data:`AUTO_ONNX_BATCH`
rows (plans, times best-of candidates), and ONNX Runtime is installed; otherwise in torch (ONNX Runtime is slower in
large batches: its convolutions lose to torch's there). The same seed, batch and installation give the same plans,
and the runtime that ran is reported with them (``api.Plans.runtime``). An exporter that cannot take the network
leaves ``auto`` on torch, with a warning.

Needs onnx (the export) and onnxruntime, both dependencies of cdrb.

``compile`` runs the network through ``torch.compile`` (TorchInductor), on the CPU or a GPU: it fuses the U-Net's
normalisations, activations and additions into a few generated kernels, which pays where the number of kernels, not
arithmetic, sets the time (a GPU at any batch up to a few hundred plans; the CPU in large batches). Its first call in
a process compiles for a while (tens of seconds; a cache under the temporary folder shortens later ones), so it serves
long runs and servers, not one `cdrb plan`. Each batch size gets its own compiled graph (the first call at a size
compiles it). Like ``onnx`` it is other kernels for the same network: plans agree with torch's to float rounding, and
in one process the same seed and batch size give the same plans (on a GPU Inductor may time kernel variants on the
device, so two processes may differ by rounding). Needs a C++ compiler and Python's headers on the CPU, Triton and a C
compiler on a GPU.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

from cdrb_cli.errors import BadInput
from cdrb_cli.lazy import torch
from cdrb_cli.settings import clip

#: the runtimes sampling's network calls may use
RUNTIMES = ("torch", "onnx", "compile", "auto")
#: the largest batch ``auto`` runs in ONNX Runtime: its lower cost per operator wins while operators, not
#: arithmetic, set a call's time, and torch's convolutions win from about 32 plans (docs/benchmarks.md §11)
AUTO_ONNX_BATCH = 16


def check_runtime(runtime: object, net, device, method: str, flag: str = "runtime") -> str:
    """``runtime`` checked for ``method``'s network and device, with one-line errors naming ``flag``."""
    if runtime not in RUNTIMES:
        raise BadInput(
            f"{flag} = {clip(repr(runtime), 40)}: not a runtime", hint=f"pass one of {', '.join(map(repr, RUNTIMES))}"
        )
    if runtime in ("torch", "auto"):  # auto: whatever the network, device and installation allow
        return runtime
    if not getattr(net, "traceable", False):
        raise BadInput(
            f"{flag} = {runtime!r}: is for the diffusion planners' temporal U-Net, and the {method} method's network "
            "is not one",
            hint="leave runtime out",
        )
    if runtime == "compile":
        return _check_compiler(device, flag)
    if torch.device(device).type != "cpu":
        raise BadInput(
            f"{flag} = 'onnx': runs on the CPU, not {device}", hint="pass device='cpu', or leave runtime out"
        )
    try:
        import onnx  # noqa: F401  (torch's exporter writes through it)
        import onnxruntime  # noqa: F401
    except ImportError:
        raise BadInput(
            f"{flag} = 'onnx': onnx and onnxruntime are not installed", hint="pip install onnx onnxruntime"
        ) from None
    return runtime


def onnx_available(net, device) -> bool:
    """Whether ``auto`` may run ``net`` in ONNX Runtime: a traceable network on the CPU, with onnx and onnxruntime
    importable."""
    if net is None or not getattr(net, "traceable", False) or torch.device(device).type != "cpu":
        return False
    try:
        import onnx  # noqa: F401
        import onnxruntime  # noqa: F401
    except ImportError:
        return False
    return True


def _check_compiler(device, flag: str) -> str:
    """``compile`` on ``device``: what TorchInductor builds its kernels with is there (the C++ compiler it calls and
    Python's headers on the CPU; Triton, a C compiler and Python's headers on a GPU), so a missing one is named now,
    not as a compiler's traceback at the first plan."""
    import importlib.util
    import os
    import shutil
    import sysconfig

    def missing(what: str, hint: str):
        raise BadInput(f"{flag} = 'compile': {what}", hint=f"{hint}, or leave runtime out")

    if not (Path(sysconfig.get_path("include")) / "Python.h").is_file():
        missing("Python's C headers (Python.h) are not installed", "install them (e.g. apt install python3-dev)")
    if torch.device(device).type == "cuda":
        if importlib.util.find_spec("triton") is None:
            missing("Triton is not installed", "install the Triton your torch was built with")
        cc = os.environ.get("CC")
        if not any(shutil.which(c) for c in ([cc] if cc else ["gcc", "clang", "cc"])):
            missing(f"no C compiler ({cc or 'gcc, clang or cc'}) on the PATH for Triton", "install one (e.g. gcc)")
        return "compile"
    from torch._inductor import config  # the compiler Inductor calls: $CXX, else g++

    cxx = config.cpp.cxx[-1]
    if not shutil.which(cxx):
        missing(f"no C++ compiler {cxx!r} on the PATH (Inductor calls $CXX, else g++)", "install g++ or set CXX")
    return "compile"


class CompiledNet:
    """A network through ``torch.compile``, called as the network is, ``(x, k) -> tensor``: one whole graph
    (``fullgraph``: a graph break would leave part of it uncompiled) and one static graph per batch size, so a plan
    never depends on the sizes planned before it in the process. A compile that fails is one line, not dynamo's
    traceback."""

    def __init__(self, net):
        self.module = torch.compile(net, dynamic=False, fullgraph=True)

    def __call__(self, x, k):
        from torch._dynamo.exc import TorchDynamoException
        from torch._inductor.exc import InductorError

        try:
            return self.module(x, k)
        except (TorchDynamoException, InductorError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise BadInput(
                f"runtime = 'compile': could not compile the network: {clip(first, 160)}", hint="leave runtime out"
            ) from None


class OnnxNet:
    """A network exported to ONNX (in memory) and run by ONNX Runtime on the CPU, one operator after another;
    called as the network is, ``(x, k) -> tensor``, for any batch size, in float32 (the export's dtype).

    The session is built once: it holds a copy of the weights as they were then, and torch's thread count of that
    moment (changing ``torch.set_num_threads`` later does not reach it). :meth:`holds` tells whether the network's
    weights are still those (else the caller builds a new one)."""

    def __init__(self, net, x, k):
        import inspect

        import onnxruntime as ort

        self.weights = [t.detach().clone() for t in _tensors(net)]
        buf = io.BytesIO()
        # the TorchScript-based exporter: torch >= 2.9 defaults to the dynamo one, which needs onnxscript; older
        # torch has no `dynamo` argument and only that exporter
        legacy = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
        try:
            with warnings.catch_warnings():  # the exporter's notes on its own future are not the user's business
                warnings.simplefilter("ignore")
                torch.onnx.export(
                    net, (x, k), buf, input_names=["x", "k"], output_names=["y"],
                    dynamic_axes={"x": {0: "batch"}, "k": {0: "batch"}}, opset_version=17, **legacy,
                )  # fmt: skip
            options = ort.SessionOptions()
            options.intra_op_num_threads = torch.get_num_threads()
            options.inter_op_num_threads = 1
            options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
            options.log_severity_level = 3  # errors only: its notes on unused initializers are not the user's business
            self.session = ort.InferenceSession(buf.getvalue(), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - an exporter or runtime of another version: one line, not a trace
            raise BadInput(
                f"runtime = 'onnx': this torch ({torch.__version__}) and onnxruntime could not export and load the "
                f"network: {clip(' '.join(str(exc).split()), 160)}",
                hint="leave runtime out (torch runs the same network)",
            ) from None

    def __call__(self, x, k):
        import numpy as np

        if x.dtype != torch.float32:
            raise BadInput(
                f"runtime = 'onnx': runs the network in float32, not {x.dtype}",
                hint="leave runtime out for other dtypes",
            )
        x, k = np.ascontiguousarray(x.numpy()), np.ascontiguousarray(k.numpy(), dtype=np.int64)
        return torch.from_numpy(self.session.run(None, {"x": x, "k": k})[0])

    def holds(self, net) -> bool:
        """Whether ``net``'s parameters and buffers still equal the copy the session was built from, compared by
        value: autograd's version counters miss writes through ``.data`` and ``vector_to_parameters``. About a
        millisecond for a million weights, made once per sampling call."""
        now = _tensors(net)
        return len(now) == len(self.weights) and all(
            a.shape == b.shape and a.dtype == b.dtype and torch.equal(a, b) for a, b in zip(now, self.weights)
        )


def _tensors(net) -> list:
    return [*net.parameters(), *net.buffers()]
