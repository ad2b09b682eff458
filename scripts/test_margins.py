"""How much room each learned-result bound of the test suite has, over several seeds and both thread counts.

A test marked `learning` asserts a number that training produced (a reward that rose, an accuracy, a loss
ratio) through `learning.above` / `learning.below` (tests/conftest.py). Such a bound is only safe if it holds
with room on every seed and thread count, not just on the one CI runs (seed 0, one thread). This script runs
the `learning` tests once per (seed, threads), with POSTTRAIN_TEST_SEED / POSTTRAIN_TEST_THREADS set and every
check recorded, and prints one row per check: its bound, the worst and best values seen, the worst margin
and how many runs failed it.

    python scripts/test_margins.py                       # seeds 0-3 x threads 1, 2 (~30 min on 2 cores)
    python scripts/test_margins.py --seeds 0 1 --threads 1 -k grpo
    python scripts/test_margins.py --real --threads 2     # the real-model tier's bounds too
    python scripts/test_margins.py --json margins.json   # the raw checks, for RESULTS.md ("Test margins")

Runs go one at a time: a 2-thread run beside another torch process crawls, and so would its numbers' runtime
(the numbers themselves do not depend on the load).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run_once(seed: int, threads: int, record: Path, select: str | None = None, real: bool = False) -> tuple[int, float]:
    """One pass of the `learning` tests at (seed, threads); checks are appended to `record`. Returns the
    pytest exit code and seconds."""
    env = dict(os.environ, POSTTRAIN_TEST_SEED=str(seed), POSTTRAIN_TEST_THREADS=str(threads),
               POSTTRAIN_MARGINS=str(record))
    marks = "learning" if real else "learning and not real"
    # one xdist worker per core at one thread each; a 2-thread pass runs in one process (2 x 2 threads would crawl)
    cmd = [sys.executable, "-m", "pytest", "-q", "-m", marks, "-p", "no:cacheprovider", "-n",
           "auto" if threads == 1 else "0", "tests"]
    if select:
        cmd += ["-k", select]
    t0 = time.time()
    rc = subprocess.run(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
    return rc, time.time() - t0


def summarize(checks: list[dict]) -> list[dict]:
    """One row per (test, check): bound, worst / median / best value, worst margin, runs and failures."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for c in checks:
        groups.setdefault((c["test"], c["check"]), []).append(c)
    rows = []
    for (test, check), cs in sorted(groups.items()):
        values = [c["value"] for c in cs]
        worst = min(cs, key=lambda c: c["margin"])
        rows.append({"test": test.split("::")[-1], "check": check, "op": cs[0]["op"], "bound": cs[0]["bound"],
                     "worst": worst["value"], "median": statistics.median(values),
                     "best": max(values) if cs[0]["op"] == ">" else min(values), "worst_margin": worst["margin"],
                     "worst_at": f"seed {worst['seed']}, {worst['threads']} thr", "runs": len(cs),
                     "failed": sum(c["margin"] <= 0 for c in cs)})
    return rows


def table(rows: list[dict]) -> str:
    out = ["| test | check | bound | worst | median | best | worst margin (at) | failed / runs |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['test']} | {r['check']} | {r['op']} {r['bound']:.4g} | {r['worst']:.4g} | "
                   f"{r['median']:.4g} | {r['best']:.4g} | {r['worst_margin']:.4g} ({r['worst_at']}) | "
                   f"{r['failed']} / {r['runs']} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("-k", dest="select", help="pytest -k expression: only these learning tests")
    ap.add_argument("--real", action="store_true", help="the real-model tier's learning tests too (tests/real/)")
    ap.add_argument("--json", type=Path, help="write the raw checks and the summary here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="posttrain-margins-") as tmp:
        record = Path(tmp) / "checks.jsonl"
        record.touch()
        passes = []
        for threads in args.threads:
            for seed in args.seeds:
                rc, secs = run_once(seed, threads, record, args.select, args.real)
                passes.append({"seed": seed, "threads": threads, "pytest_rc": rc, "seconds": round(secs, 1)})
                print(f"seed {seed}, {threads} thread(s): pytest exit {rc} in {secs:.0f} s", flush=True)
        checks = [json.loads(l) for l in record.read_text().splitlines() if l.strip()]
    rows = summarize(checks)
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps({"passes": passes, "summary": rows, "checks": checks}, indent=1))
    return 1 if any(r["failed"] for r in rows) else 0


if __name__ == "__main__":
    raise SystemExit(main())
