"""Run one `posttrain` CLI stage in a subprocess, as a user would (shared by the reproduction scripts).

`run_stage(["sft", "--recipe", ...], log, threads, "reproduce_e7")` writes the command and its output to `log`,
sets OMP_NUM_THREADS when `threads` > 0, and returns the wall time; a failing stage stops the script with
the log's last lines.
"""
from __future__ import annotations

import os
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
