"""Run one `posttrain` CLI stage in a subprocess, as a user would (shared by the reproduction scripts).

`run_stage(["sft", "--recipe", ...], log, threads, "reproduce_e7")` writes the command and its output to `log`,
sets OMP_NUM_THREADS when `threads` > 0, and returns the wall time; a failing stage stops the script with
the log's last lines. `prepare(args, script, default_out)` is the reproductions' shared start: it checks the
`--set` overrides, makes the output directory (empty with --fresh), sets torch's threads and quiets the libraries.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_stage(args: list[str], log: Path, threads: int, script: str) -> float:
    cmd = [sys.executable, "-m", "posttrain", *args]
    env = dict(os.environ)
    if threads:
        env["OMP_NUM_THREADS"] = str(threads)
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with open(log, "w") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    took = time.time() - t0
    if rc != 0:
        tail = "\n".join(log.read_text().splitlines()[-15:])
        raise SystemExit(f"{script}: `posttrain {args[0]}` failed (exit {rc}); log {log}:\n{tail}")
    return took


def prepare(args, script: str, default_out: Path) -> Path:
    """Check `args.overrides` (stage.key=value), make the output directory (`args.out` or `default_out`; emptied
    under `args.fresh`), set torch's threads (`args.threads`, 0: its default), quiet datasets' and transformers'
    progress bars and warnings; the output directory."""
    for o in args.overrides:
        if "=" not in o or "." not in o.split("=", 1)[0]:
            raise SystemExit(f"{script}: --set {o!r} must look like stage.key=value (e.g. grpo.max_steps=100)")
    out = (args.out or default_out).resolve()
    if args.fresh and out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    import datasets
    import transformers

    datasets.disable_progress_bars()
    transformers.utils.logging.set_verbosity_error()
    transformers.utils.logging.disable_progress_bar()
    return out
