"""Where sampling's network calls run: torch (the default), ONNX Runtime on the CPU, or torch's compiler.

At batch 1 a small temporal U-Net costs torch ~400 operator dispatches per pass, and that per-operation cost, not
arithmetic, is most of a plan's time on a CPU (a robot re-planning one plan at a time, the Python API).
ONNX Runtime runs the same network, exported once to memory, through its own CPU kernels at a fraction of that cost
per operation. It is the same network in another library's kernels: outputs agree with torch's to float rounding,
not bit for bit, and a ball sampler that meets a state on a ball's edge may then draw another buffer state, so the
runtime is a setting the caller chooses (``api.Planner(runtime="onnx")``), never a silent switch. Within one
runtime, plans are as reproducible as torch's: the same seed gives the same plans.

Needs the ``onnx`` extra (``pip install 'cdrb[onnx]'``: onnx for the export, onnxruntime to run it).

``compile`` runs the network through ``torch.compile`` (TorchInductor), on the CPU or a GPU: it fuses the U-Net's
normalisations, activations and additions into a few generated kernels, which pays where the number of kernels, not
arithmetic, sets the time (a GPU at any batch up to a few hundred plans; the CPU in large batches). Its first call in
a process compiles for a while (tens of seconds; a cache under the temporary folder shortens later ones), so it serves
long runs and servers, not one `cdrb plan`. Like ``onnx`` it is other kernels for the same network: plans agree with
torch's to float rounding, and the same seed gives the same plans. Needs a C++ compiler on the CPU, Triton on a GPU.
"""

from __future__ import annotations

import io
import warnings

from cdrb_cli.errors import BadInput
from cdrb_cli.lazy import torch
from cdrb_cli.settings import clip

#: the runtimes sampling's network calls may use
RUNTIMES = ("torch", "onnx", "compile")


def check_runtime(runtime: object, net, device, method: str, flag: str = "runtime") -> str:
    """``runtime`` checked for ``method``'s network and device, with one-line errors naming ``flag``."""
    if runtime not in RUNTIMES:
        raise BadInput(
            f"{flag} = {clip(repr(runtime), 40)}: not a runtime", hint=f"pass one of {', '.join(map(repr, RUNTIMES))}"
        )
    if runtime == "torch":
        return runtime
    if not getattr(net, "traceable", False):
        where = "in ONNX Runtime" if runtime == "onnx" else "compiled"
        raise BadInput(
            f"{flag} = {runtime!r}: the {method} method's network does not run {where} (the temporal U-Net of the "
            "diffusion planners does)",
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
            f"{flag} = 'onnx': onnx and onnxruntime are not installed", hint="pip install 'cdrb[onnx]'"
        ) from None
    return runtime


def _check_compiler(device, flag: str) -> str:
    """``compile`` on ``device``: TorchInductor's code generator is there (a C++ compiler for the CPU, Triton for a
    GPU), so a missing one is named now, not as a compiler's traceback at the first plan."""
    import importlib.util
    import os
    import shutil

    if torch.device(device).type == "cuda":
        if importlib.util.find_spec("triton") is None:
            raise BadInput(
                f"{flag} = 'compile': Triton is not installed", hint="pip install triton, or leave runtime out"
            )
        return "compile"
    cxx = os.environ.get("CXX")
    if not any(shutil.which(c) for c in ([cxx] if cxx else ["g++", "clang++"])):
        raise BadInput(
            f"{flag} = 'compile': no C++ compiler ({cxx or 'g++ or clang++'}) on the PATH",
            hint="install one (e.g. apt install g++), or leave runtime out",
        )
    return "compile"


class OnnxNet:
    """A network exported to ONNX (in memory) and run by ONNX Runtime on the CPU, one operator after another;
    called as the network is, ``(x, k) -> tensor``, for any batch size, in float32 (the export's dtype).

    The session is built once: it holds a copy of the weights as they were then, and torch's thread count of that
    moment (changing ``torch.set_num_threads`` later does not reach it). :func:`weights_version` tells whether the
    weights changed since (the caller then builds a new one)."""

    def __init__(self, net, x, k):
        import inspect

        import onnxruntime as ort

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


def weights_version(net) -> tuple[int, ...]:
    """The version counters of ``net``'s parameters and buffers: every in-place change (an optimizer step,
    ``load_state_dict``) bumps one, so a session built at another version runs stale weights."""
    return tuple(t._version for t in (*net.parameters(), *net.buffers()))
