"""Benchmark the verifier layer: math verdicts per second, and the code sandbox's cost per candidate.

    python scripts/bench_verifiers.py            # ~10 s on 2 CPU cores
    python scripts/bench_verifiers.py --quick    # ~2 s
    python scripts/bench_verifiers.py --json bench_verifiers.json

What it measures, side by side in one run:
1. math, simple numeric: completions of ~250 characters of arithmetic reasoning that end in
   `\\boxed{N}`, "The answer is N.", `#### N` or a bare number (a quarter of them wrong),
   scored through `VerifierPool(workers=1).score(...)` (the batch API a trainer calls, one
   worker process, per-check time limit on). Reports verdicts/second against the 500/s
   target, the same verdicts computed by direct in-process `check` calls, and the ratio
   (what worker isolation costs). Best of 3 passes (1 with --quick) for both.
2. math, mix: the gold completions of `MathVerifier.audit_problems` (integers, fractions,
   decimals, percentages, sqrt, pi, sets, intervals, tuples, polynomials, equations,
   scientific notation, letters), i.e. the sympy paths too, on one worker.
3. code sandbox, only if `posttrain.verifiers.code_sandbox` imports: wall milliseconds per trivial
   candidate (`def add(a, b): return a + b` against one assert) scored one at a time, next to
   a bare `python -c pass` start; the difference is the sandbox's added overhead per
   candidate (harness, namespaces, fork, cleanup) on top of an interpreter start.
Timings are wall clock on whatever else the machine runs; compare ratios within one run.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from posttrain.verifiers import VerifierPool, get_verifier  # noqa: E402


def simple_numeric(n: int, seed: int = 0) -> tuple[list[str], list[str]]:
    rng = random.Random(seed)
    completions, references = [], []
    for _ in range(n):
        a, b, c = rng.randint(2, 999), rng.randint(2, 99), rng.randint(2, 99)
        value = a + b * c
        answer = value if rng.random() < 0.75 else value + rng.randint(1, 9)
        reasoning = (f"First compute {b} times {c}, which is {b * c}. Then add {a} to get {a} + {b * c}. "
                     f"Checking: {b * c} + {a} = {a + b * c}. ")
        ending = rng.choice([f"The answer is {answer}.", f"\\boxed{{{answer}}}", f"#### {answer}", f"So it is {answer}"])
        completions.append(reasoning + ending)
        references.append(str(value))
    return completions, references


def rate(verifier, completions, references, workers: int, repeats: int) -> dict:
    best = float("inf")
    with VerifierPool(workers=workers) as pool:
        pool.score(verifier, completions[:8], references[:8])  # start + warm the worker
        for _ in range(repeats):
            t0 = time.perf_counter()
            verdicts = pool.score(verifier, completions, references)
            best = min(best, time.perf_counter() - t0)
    passed = sum(v.passed for v in verdicts)
    return {"items": len(completions), "seconds": best, "per_second": len(completions) / best, "passed": passed}


def in_process_rate(verifier, completions, references, repeats: int) -> dict:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for c, r in zip(completions, references):
            verifier.check(c, r)
        best = min(best, time.perf_counter() - t0)
    return {"items": len(completions), "seconds": best, "per_second": len(completions) / best}


def code_overhead(n: int) -> dict | None:
    try:
        from posttrain.verifiers.code_sandbox import CodeVerifier
    except Exception as e:  # not installed in this checkout
        return {"skipped": f"posttrain.verifiers.code_sandbox unavailable ({type(e).__name__}: {e})"}
    verifier = CodeVerifier()
    reference = {"tests": ["assert add(1, 2) == 3"], "entry_point": "add"}
    completion = "```python\ndef add(a, b):\n    return a + b\n```"
    first = verifier.check(completion, reference)
    if not first.passed:
        return {"skipped": f"trivial candidate did not pass ({first.reason}); sandbox unusable here"}
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        verifier.check(completion, reference)
        times.append(time.perf_counter() - t0)
    bare = []
    for _ in range(max(3, n // 2)):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-S", "-c", "pass"], check=True)
        bare.append(time.perf_counter() - t0)
    times.sort()
    bare.sort()
    med, bare_med = times[len(times) // 2], bare[len(bare) // 2]
    return {"mode": first.details.get("mode"), "ms_per_candidate": med * 1000, "bare_python_ms": bare_med * 1000,
            "added_overhead_ms": (med - bare_med) * 1000}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer items and repeats")
    parser.add_argument("--json", metavar="OUT", help="also write the numbers as JSON")
    args = parser.parse_args(argv)
    n_simple, n_mix, repeats, n_code = (2000, 150, 1, 5) if args.quick else (8000, 600, 3, 20)

    math_v = get_verifier("math")
    results: dict = {}
    comps, refs = simple_numeric(n_simple)
    results["math_simple_1_worker"] = rate(math_v, comps, refs, workers=1, repeats=repeats)
    results["math_simple_in_process"] = in_process_rate(math_v, comps, refs, repeats)
    problems = math_v.audit_problems(n_mix, seed=1)
    mix_c, mix_r = [p.gold for p in problems], [p.reference for p in problems]
    results["math_mix_1_worker"] = rate(math_v, mix_c, mix_r, workers=1, repeats=repeats)
    results["code_sandbox"] = code_overhead(n_code)

    s, p, m = results["math_simple_1_worker"], results["math_simple_in_process"], results["math_mix_1_worker"]
    print(f"math, simple numeric, 1 worker : {s['per_second']:8.0f} verdicts/s  ({s['items']} items, "
          f"{s['passed']} passed; target >= 500/s: {'OK' if s['per_second'] >= 500 else 'BELOW TARGET'})")
    print(f"math, simple numeric, in-process: {p['per_second']:8.0f} verdicts/s  "
          f"(the worker path runs at {100 * s['per_second'] / p['per_second']:.0f}% of this)")
    print(f"math, mix (sympy paths), 1 worker: {m['per_second']:7.0f} verdicts/s  ({m['items']} items, {m['passed']} passed)")
    code = results["code_sandbox"]
    if "skipped" in code:
        print(f"code sandbox: skipped: {code['skipped']}")
    else:
        print(f"code sandbox ({code['mode']}): {code['ms_per_candidate']:.1f} ms per candidate, bare python start "
              f"{code['bare_python_ms']:.1f} ms -> sandbox adds {code['added_overhead_ms']:.1f} ms per candidate")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(results, f, indent=2)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
