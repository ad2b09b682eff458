"""The learning check: short, fixed training runs whose held-out figures are compared with bands recorded in RESULTS.md.

Run it before every stop that changes a trainer, a loss, the rollout engine, a precision path or a seed stream
(quick), and before calling such an issue resolved (full). It is a script, not a test: it trains, takes minutes, and
its bands are spreads over seeds measured on real CPUs, never timed assertions.

CPU:  python scripts/learning_check.py                quick tier: tiny-math from nothing (1500 SFT steps, then 40
                                                      GRPO steps), two seeds side by side
      python scripts/learning_check.py --full         adds tiny-calc (its recipe's SFT, then 30 multi-turn GRPO steps
                                                      with the calculator) and smol-math (the recipe's 40 LoRA GRPO
                                                      steps on SmolLM2-135M-Instruct), two seeds (`posttrain models
                                                      fetch smollm2-135m-instruct models/smollm2-135m-instruct` first)
      python scripts/learning_check.py --record --seeds 0-4 [--only NAME]
                                                      the per-seed figures and band rows for RESULTS.md
Runtimes (RESULTS.md, "The learning check"): the runs go in parallel, one torch thread each (`--jobs`, default 2:
two cores), so a tier takes about as long as its longest run.

Each run is one `python -m posttrain grpo --recipe ...` command with fixed overrides (`RUNS`), in a run directory of
its own under --out; its figures are read from the stage's eval.json: the SFT model's and the GRPO model's held-out
greedy accuracy on the same problems, and their difference. Each figure is compared with its band for the precision
the run computes in: the tiny recipes train and sample in fp32 on every machine; smol-math's `auto` settings give
bf16 where it is native and faster, fp32 elsewhere (`--precision fp32|bf16` sets both the training autocast and the
rollout weights for every run instead; `--precision fp32,bf16` runs each seed in both, one right after the other,
in run directories NAME-sSEED-PRECISION). Below the band's lowest seed is FAIL, above its highest is "above" (a pass
worth a look), no band recorded for that precision is "no band". A band wider than 5 points cannot
catch a 5-point drop: the check says so next to it. The bands live in RESULTS.md between the markers
`<!-- learning-check-bands -->` and `<!-- /learning-check-bands -->`, one row per (run, figure, precision):

    | run | figure | precision | seeds | per seed | band |
    |---|---|---|---|---|---|
    | tiny-math | grpo | fp32 | 0-4 | 0.900 0.915 ... | 0.900-0.985 |

Exit status: 0 when every figure with a band is in or above it, 1 when one is below, 2 when a run itself failed (its
log's tail printed), 3 when no figure had a band for this precision (nothing was checked).
Options: --out DIR (default runs/learning-check), --seeds (default: each run's own), --only NAME[,NAME], --jobs N,
--set STAGE.KEY=VALUE (an experiment on every run: printed, never compared with the bands),
--model DIR (the real model; default models/smollm2-135m-instruct), --results FILE (default RESULTS.md), --json FILE.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- learning-check-bands -->", "<!-- /learning-check-bands -->"
FIGURES = ("sft", "grpo", "gain")  # held-out greedy accuracy of the SFT model, of the GRPO model, and their difference
CATCH = 0.05  # a band wider than this cannot tell a 5-point drop from seed luck


@dataclass(frozen=True)
class Run:
    """One fixed run of the check: a recipe, its overrides, the seed keys to set, its tier, the seeds it runs."""

    name: str
    recipe: str
    overrides: tuple[str, ...]
    seed_keys: tuple[str, ...]
    tier: str  # "quick" or "full"
    seeds: tuple[int, ...]
    real: bool = False  # needs the real model (--model)

    def command(self, seed: int, out: Path, model: str, precision: str = "recipe",
                sets: tuple[str, ...] = ()) -> list[str]:
        keys = [f"{k}={seed}" for k in self.seed_keys]
        extra = [f"model.path={model}"] if self.real else []
        return [sys.executable, "-m", "posttrain", "grpo", "--recipe", self.recipe, "run.threads=1",
                f"run.output_dir={out}", "run.quiet=true", *extra, *keys, *self.overrides, *PRECISIONS[precision],
                *sets]

    def precision(self, choice: str) -> str:
        """fp32 or bf16: what this run computes in under `choice` (recipe: the recipe's own settings, `auto`
        resolved on this machine at one torch thread, as the run resolves it)."""
        if choice != "recipe":
            return choice
        from posttrain.cli import validate

        run = next(res for res in validate(self.recipe, list(self.overrides)) if res.stage == "grpo")
        settings = {run.run.mixed_precision, run.rollout.dtype}
        if "auto" in settings:
            import torch

            from posttrain import runtime

            threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                if runtime.native_bf16():
                    return "bf16"
            finally:
                torch.set_num_threads(threads)
        return "bf16" if settings & {"bf16", "bfloat16"} else "fp32"


# --precision: the recipes' own settings, or both the training autocast and the rollout weights set to one precision
# (bf16 runs anywhere; where it is not native it is emulated and slower, with bf16's rounding all the same), or one
# of the two in bf16 and the other in fp32: which half of bf16 costs learning, where it does.
PRECISIONS = {"recipe": (), "fp32": ("run.mixed_precision=no", "rollout.dtype=float32"),
              "bf16": ("run.mixed_precision=bf16", "rollout.dtype=bfloat16"),
              "bf16-train": ("run.mixed_precision=bf16", "rollout.dtype=float32"),
              "bf16-rollout": ("run.mixed_precision=no", "rollout.dtype=bfloat16")}


# The runs. Their sizes are chosen so that a run learns something visible in a few minutes of one core, and changing
# them changes their bands: record new bands (--record) in the same commit.
RUNS = (
    # tiny-math: a tokenizer and a ~1M model from nothing, 1500 SFT steps (worked answers mostly right, the
    # direct-style question answered without working), then 40 GRPO steps that learn to work every question. At 800
    # SFT steps the copy-the-numbers skill had appeared for seed 0 (SFT 0.375) and not for seed 1 (0.055): too
    # close to the step where it appears to give a band; after 20 GRPO steps seed 0 had not moved (0.610 -> 0.610)
    # and seed 1 had (0.640 -> 0.955): the step where GRPO takes off varies too (RESULTS.md, "The learning check").
    Run("tiny-math", "tiny-math",
        ("sft.max_steps=1500", "sft.eval_every=0", "sft.save_every=0", "sft.final_eval_rows=0",
         "grpo.max_steps=40", "grpo.eval_every=0", "grpo.save_every=0", "grpo.final_eval_rows=200"),
        ("model.seed", "sft.seed", "grpo.seed"), "quick", (0, 1)),
    # tiny-calc: the recipe's 1200 SFT steps on demonstrations of which 40% call the calculator, then 30 multi-turn
    # GRPO steps in the calc environment, which learn to call it. In the full tier: its SFT alone takes ~10 min
    # on Zen 4, and shorter ones teach no copy of the tool's result (300 steps x 32 rows, 800 x 16: SFT copy
    # 0.01 / 0.33, GRPO reward 0 at every step; RESULTS.md, "The learning check").
    Run("tiny-calc", "tiny-calc",
        ("sft.eval_every=0", "sft.save_every=0", "sft.final_eval_rows=0",
         "grpo.max_steps=30", "grpo.eval_every=0", "grpo.save_every=0", "grpo.final_eval_rows=200"),
        ("model.seed", "sft.seed", "grpo.seed"), "full", (0,)),
    # smol-math: SmolLM2-135M-Instruct as it is, the recipe's 40 LoRA GRPO steps on word problems (E7 real's GRPO
    # stage), its 200 held-out problems before and after; no evaluations or checkpoints in between.
    Run("smol-math", "smol-math",
        ("grpo.eval_every=0", "grpo.save_every=0", "grpo.final_eval_rows=200"),
        ("grpo.seed",), "full", (0, 1), real=True),
)


def parse_seeds(text: str) -> tuple[int, ...]:
    """"0-4" or "0,2,5" -> the seeds; a clear error otherwise."""
    try:
        if "-" in text:
            lo, hi = (int(x) for x in text.split("-", 1))
            if hi < lo:
                raise ValueError
            return tuple(range(lo, hi + 1))
        return tuple(int(x) for x in text.split(","))
    except ValueError:
        raise SystemExit(f"learning_check: --seeds {text!r} must look like 0-4 or 0,2,5") from None


def read_bands(path: Path) -> dict[tuple[str, str, str], tuple[float, float, str]]:
    """{(run, figure, precision): (low, high, seeds)} from the marked table in `path` (RESULTS.md)."""
    text = path.read_text() if path.exists() else ""
    if BEGIN not in text or END not in text:
        return {}
    bands = {}
    for line in text.split(BEGIN, 1)[1].split(END, 1)[0].splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 6 or cells[0] in ("run", "") or set(cells[0]) <= {"-"}:
            continue
        run, figure, precision, seeds, _, band = cells
        m = re.fullmatch(r"(-?[\d.]+)\s*(?:to|\.\.|-)\s*(-?[\d.]+)", band.replace("**", ""))
        if not m:
            raise SystemExit(f"learning_check: {path}: band {band!r} of {run} / {figure} / {precision} must read LOW-HIGH")
        bands[(run, figure, precision)] = (float(m.group(1)), float(m.group(2)), seeds)
    return bands


def verdict(value: float, band: tuple[float, float, str] | None) -> str:
    if band is None:
        return "no band"
    low, high, _ = band
    if value < low - 1e-9:
        return "FAIL"
    return "above" if value > high + 1e-9 else "pass"


def figures_of(run_dir: Path, recipe: str) -> dict[str, float]:
    """SFT and GRPO held-out greedy accuracy (and the gain) from a finished run's grpo/eval.json."""
    ev = json.loads((run_dir / recipe / "grpo" / "eval.json").read_text())
    sft, grpo = ev["sft"]["eval/accuracy"], ev["grpo"]["eval/accuracy"]
    return {"sft": sft, "grpo": grpo, "gain": grpo - sft}


def run_one(run: Run, seed: int, out: Path, model: str, precision: str, env: dict[str, str],
            tag: bool = False, sets: tuple[str, ...] = ()) -> dict:
    run_dir = out / (f"{run.name}-s{seed}" + (f"-{precision}" if tag else ""))
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    log = run_dir / "log.txt"
    cmd = run.command(seed, run_dir, model, precision, sets)
    t0 = time.time()
    with open(log, "w") as f:
        f.write("$ " + " ".join(cmd[1:]) + "\n")
        f.flush()
        rc = subprocess.call(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    took = time.time() - t0
    if rc != 0:
        tail = "\n".join(log.read_text().splitlines()[-12:])
        return {"run": run.name, "seed": seed, "seconds": took, "error": f"exit {rc}; {log}:\n{tail}"}
    return {"run": run.name, "seed": seed, "seconds": took, **figures_of(run_dir, run.recipe)}


def band_rows(results: list[dict]) -> list[str]:
    """Markdown rows of the bands table from `results` (several seeds of each run, each with its precision)."""
    rows = []
    for name, precision in dict.fromkeys((r["run"], r["precision"]) for r in results):
        done = sorted((r for r in results if (r["run"], r["precision"]) == (name, precision) and "error" not in r),
                      key=lambda r: r["seed"])
        if not done:
            continue
        seeds = ",".join(str(r["seed"]) for r in done)
        for fig in FIGURES:
            vals = [r[fig] for r in done]
            rows.append(f"| {name} | {fig} | {precision} | {seeds} | {' '.join(f'{v:.3f}' for v in vals)} | "
                        f"{min(vals):.3f}-{max(vals):.3f} |")
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="add the real-model runs")
    ap.add_argument("--record", action="store_true", help="print band rows for RESULTS.md from the seeds run")
    ap.add_argument("--seeds", default="", help="seeds of every run (0-4, 0,2); default: each run's own")
    ap.add_argument("--only", default="", help="run only these runs (comma-separated names)")
    ap.add_argument("--jobs", type=int, default=2, help="runs in parallel, one torch thread each (default 2)")
    ap.add_argument("--precision", default="recipe",
                    help="recipe (default: each recipe's own settings), fp32 / bf16 for training and rollouts, "
                         "bf16-train / bf16-rollout for one of them; fp32,bf16 runs each seed in both, one right "
                         "after the other")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.KEY=VALUE",
                    help="an override for every run (an experiment: its figures are printed, never compared with "
                         "the bands; repeatable)")
    ap.add_argument("--model", default="models/smollm2-135m-instruct")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "learning-check")
    ap.add_argument("--results", type=Path, default=ROOT / "RESULTS.md")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here (default OUT/results.json)")
    args = ap.parse_args(argv)

    names = {r.name for r in RUNS}
    only = {n.strip() for n in args.only.split(",") if n.strip()}
    if only - names:
        raise SystemExit(f"learning_check: unknown run(s) {', '.join(sorted(only - names))}; "
                         f"choose from {', '.join(r.name for r in RUNS)}")
    runs = [r for r in RUNS if (r.name in only if only else (r.tier == "quick" or args.full))]
    if args.jobs < 1:
        raise SystemExit(f"learning_check: --jobs must be at least 1, got {args.jobs}")
    if any(r.real for r in runs) and not (Path(args.model) / "config.json").exists():
        raise SystemExit(f"learning_check: the real model is not at {args.model}; run `posttrain models fetch "
                         f"smollm2-135m-instruct {args.model}` first, or give --model DIR")
    seeds = parse_seeds(args.seeds) if args.seeds else None
    choices = list(dict.fromkeys(p.strip() for p in args.precision.split(",") if p.strip()))
    if not choices or set(choices) - set(PRECISIONS):
        raise SystemExit(f"learning_check: --precision {args.precision!r}: choose from {', '.join(PRECISIONS)} "
                         "(or several, comma-separated)")
    bands = read_bands(args.results)
    precision = {(r.name, c): r.precision(c) for r in runs for c in choices}
    env = dict(os.environ, OMP_NUM_THREADS="1")
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    # each seed in every precision asked for, one right after the other (side by side with --jobs 2)
    jobs = [(r, s, c) for r in runs for s in (seeds or r.seeds) for c in choices]
    print(f"[learning-check] {len(jobs)} run(s): "
          f"{', '.join(f'{r.name} seed {s} ({precision[r.name, c]})' for r, s, c in jobs)}"
          f"; {args.jobs} at a time, one thread each; logs under {out}", flush=True)
    t0 = time.time()
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(lambda job: {**run_one(job[0], job[1], out, args.model, job[2], env,
                                                       tag=len(choices) > 1, sets=tuple(args.sets)),
                                             "precision": precision[job[0].name, job[2]]}, jobs))
    wall = time.time() - t0

    failed = worst = checked = 0
    for r in results:
        if "error" in r:
            print(f"[learning-check] {r['run']} seed {r['seed']}: the run failed ({r['error']})")
            failed += 1
            continue
        parts = []
        for fig in FIGURES:
            band = None if args.sets else bands.get((r["run"], fig, r["precision"]))
            v = verdict(r[fig], band)
            worst += v == "FAIL"
            checked += band is not None
            notes = [n for n, on in (("wider than 5 points: a 5-point drop can hide in it", band and band[1] - band[0] > CATCH),
                                     ("fewer than 5 seeds: provisional", band and len(parse_seeds(band[2])) < 5)) if on]
            where = (f" [{band[0]:.3f}, {band[1]:.3f}] over seeds {band[2]}"
                     + (f" ({'; '.join(notes)})" if notes else "")) if band else ""
            parts.append(f"{fig} {r[fig]:.3f} {v}{where}")
        print(f"[learning-check] {r['run']} seed {r['seed']} ({r['precision']}, {r['seconds'] / 60:.1f} min): "
              + "; ".join(parts))
    status = 2 if failed else (1 if worst else (0 if checked else 3))
    word = {0: "PASS", 1: "FAIL", 2: "FAIL", 3: "UNCHECKED"}[status]
    if args.sets:
        print(f"[learning-check] with --set {' '.join(args.sets)}: an experiment, not compared with the bands")
    print(f"[learning-check] {word}: {checked} figure(s) compared with a band, {worst} below it, {failed} run(s) "
          f"failed; {wall / 60:.1f} min in all", flush=True)
    if args.record:
        print("\n".join(band_rows(results)))
    summary = {"precision": ",".join(choices), "set": args.sets, "wall_s": round(wall, 1), "status": status, "results": results}
    (args.json or out / "results.json").write_text(json.dumps(summary, indent=1) + "\n")
    return status


if __name__ == "__main__":
    sys.exit(main())
