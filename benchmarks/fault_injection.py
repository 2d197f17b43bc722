"""Inject faults into real cdrb processes and report what survived (the table in docs/reliability.md).

For each stage (collect, cluster, train, eval, tiny settings): SIGKILL at N random moments of its run, check the
output (absent, or a valid artifact: an unfinished training checkpoint counts as valid), re-run (with --resume when
a checkpoint was left) and compare with an uninterrupted run. Then crash every writer between writing and renaming
(CDRB_CRASH_BEFORE_RENAME=1) and check the previous artifact is intact.

Usage: python benchmarks/fault_injection.py [--kills 20] [--seed 0] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fault_harness import crash_before_rename, run_faults  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--kills", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path)
    args = ap.parse_args()
    root = args.workdir or Path(tempfile.mkdtemp(prefix="cdrb-faults-"))
    t = time.time()
    stats = run_faults(root, args.kills, args.seed)
    crashed = crash_before_rename(root)
    print(
        f"| fault | stage | injected | output absent | unfinished checkpoint left | corrupt outputs | "
        f"re-run differs from uninterrupted | temp files left |  ({time.time() - t:.0f}s)"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, s in stats.items():
        print(
            f"| SIGKILL at a random moment | {name} | {s.kills} | {s.killed_before_output} | "
            f"{s.killed_with_checkpoint} | {s.output_corrupt} | {s.rerun_mismatch} | {s.temp_files_left} |"
        )
    for name, ok in crashed.items():
        print(f"| crash between write and rename | {name} | 1 | – | – | {0 if ok else 1} | – | – |")


if __name__ == "__main__":
    main()
