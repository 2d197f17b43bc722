"""Throughput of the ball sampler (the degradation D), ours vs the reference approach.

Reference approach (re-implemented here from its description, see docs/benchmarks.md): for B*H query states and K
buffer points, compute the full (B*H, K) distance matrix through a (B*H, K, D) difference tensor, mask the ball,
append an "empty ball" column, draw with torch.multinomial, and gather from the buffer repeated to (B*H, K+1, D).
Its memory grows as B*H*K*D, so at K = 100,000 it only runs on small batches.

Ours: cdrb_cli.buffer.BallSampler (rejection rounds + KD-tree enumeration, exact, no (B*H, K, D) tensor). Also
timed, on ``--device``: the torch sampler that training uses on a GPU (TorchBallSampler, rejection rounds + dense
enumeration of the rest) and the dense baseline (cdist to all K points + masked Gumbel-max for every query).

Usage: python benchmarks/sampler_throughput.py [--demos demos.h5] [--repeats 5] [--device cuda] [--json out.json]
Without --demos it collects 1,000 Maze Tight demos first (about 20 s).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from functools import partial
from pathlib import Path

import numpy as np
import torch

from cdrb_cli.buffer import BallSampler, Normalizer, TorchBallSampler, radii


def reference_degrade(x: torch.Tensor, buffer: torch.Tensor, radius: torch.Tensor, gen) -> torch.Tensor:
    B, H, D = x.shape
    flat = x.reshape(-1, D)
    dist = torch.norm(buffer[None, :, :] - flat[:, None, :], dim=-1)  # (BH, K), via a (BH, K, D) tensor
    mask = dist < radius.repeat_interleave(H)[:, None]
    empty = ~mask.any(dim=1, keepdim=True)
    weights = torch.cat([mask, empty], dim=1).float()
    idx = torch.multinomial(weights, 1, generator=gen).squeeze(1)
    cand = torch.cat([buffer[None].repeat(flat.shape[0], 1, 1), flat[:, None, :]], dim=1)  # (BH, K+1, D)
    return cand[torch.arange(flat.shape[0]), idx].reshape(B, H, D)


def states(demos_path: Path | None) -> np.ndarray:
    from cdrb_cli import artifacts

    if demos_path is None:
        import tempfile

        from cdrb_cli.envs.registry import make_spec
        from cdrb_cli.stages.collect import collect, collect_config

        spec = make_spec("maze-tight")
        demos_path = Path(tempfile.mkdtemp()) / "demos.h5"
        collect(spec, collect_config(spec, 1000, seed=0), demos_path)
    d = artifacts.load(demos_path, "demos")
    x = d.observations.astype(np.float64)
    return Normalizer.fit(x).normalize(x)


def bench(fn, repeats: int, sync=lambda: None) -> float:
    fn()  # warm-up (KD-tree build, caches, allocator)
    sync()
    t = time.perf_counter()
    for _ in range(repeats):
        fn()
    sync()
    return (time.perf_counter() - t) / repeats


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--demos", type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--device", default="cpu", help="where the torch samplers run (cpu, cuda)")
    args = ap.parse_args()
    dev = torch.device(args.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    torch.set_num_threads(2)
    z = states(args.demos)
    rng = np.random.default_rng(0)
    T, H = 128, 168
    results = []
    for K, ref_batch in ((1000, 64), (100_000, 2)):
        pts = z[rng.choice(len(z), K, replace=False)]
        eps = radii("linear", float(np.linalg.norm(pts.max(0) - pts.min(0))), T)
        ours = BallSampler(pts, eps)
        on_device = {s: TorchBallSampler(pts, eps, device=dev, strategy=s) for s in ("auto", "dense")}
        buf_t = torch.as_tensor(pts, dtype=torch.float32)
        for batch in sorted({ref_batch, 64}):
            x = z[rng.integers(len(z), size=(batch, H))]
            for regime in ("training (k ~ U{1..T-1})", "sampling (one k per call)"):
                ks = rng.integers(1, T, size=batch) if regime.startswith("training") else np.full(batch, T // 2)
                n = batch * H
                t_ours = bench(partial(ours.degrade, x, ks, rng), args.repeats)
                row = {"K": K, "batch": batch, "queries": n, "regime": regime, "ours_states_per_s": n / t_ours}
                xd = torch.as_tensor(x, dtype=torch.float32, device=dev)
                for name, sampler in on_device.items():
                    gen = sampler.generator(rng)
                    t = bench(partial(sampler.degrade, xd, ks, gen), args.repeats, sync)
                    row[f"torch_{name}_states_per_s"] = n / t
                mem = n * (K + 1) * 4 * 4 * 2  # the (BH, K, D) difference and (BH, K+1, D) gather, float32
                if batch <= ref_batch:
                    xt = torch.as_tensor(x, dtype=torch.float32)
                    rt = torch.as_tensor(eps[ks], dtype=torch.float32)
                    gen = torch.Generator().manual_seed(0)
                    t_ref = bench(partial(reference_degrade, xt, buf_t, rt, gen), args.repeats)
                    row["reference_states_per_s"] = n / t_ref
                    row["speedup"] = t_ref / t_ours
                else:
                    row["reference_states_per_s"] = None
                row["reference_tensor_GiB"] = mem / 2**30
                results.append(row)
                ref = row["reference_states_per_s"]
                print(
                    f"K={K:>7,} batch={batch:>3} {regime:28s} ours {n / t_ours:>12,.0f} states/s   reference "
                    + (
                        f"{ref:>12,.0f} states/s  ({row['speedup']:.1f}x)"
                        if ref
                        else f"{'not run':>12s} (needs {mem / 2**30:,.0f} GiB)"
                    )
                    + f"   torch on {dev}: {row['torch_auto_states_per_s']:>12,.0f}, dense baseline "
                    + f"{row['torch_dense_states_per_s']:>12,.0f} states/s"
                )
    meta = {
        "machine": f"{platform.processor() or platform.machine()}, torch threads 2",
        "device": str(dev) if dev.type != "cuda" else torch.cuda.get_device_name(dev),
        "torch": torch.__version__,
        "results": results,
    }
    if args.json:
        args.json.write_text(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
