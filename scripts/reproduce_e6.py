"""E6 (seed §16): small-scale RLHF on tiny-summarize: DPO against PPO-for-RLHF on the same preference data.

The seed's claim (the DPO paper's setting): on the same preference pairs, DPO is simpler and more stable than
PPO against a reward model trained on those pairs. The script runs ARMS, each from one shared SFT model:

  like with like (the headline; the very pairs the reward model was trained on, prefs/final/train.jsonl):
    dpo-offline      DPO on those pairs (`dpo.online=false`, no train_file: the prefs stage output)
    ppo-rm           PPO against the reward model trained on those pairs (`ppo.reward=rm`)
    simpo-offline    SimPO on those pairs (`dpo.loss_type=simpo dpo.beta=2.0 dpo.simpo_gamma=0.5`)
    orpo-offline     ORPO on those pairs (`dpo.loss_type=orpo dpo.beta=0.1`)
    kto-offline      KTO on those pairs unpaired: each chosen side a desirable row, each rejected side an
                     undesirable one (`dpo.loss_type=kto dpo.beta=0.1`)
  oracle (gold labels or the gold reward; NOT the seed's setting, an upper reference):
    dpo-online-gold  the recipe's online DPO: pairs regenerated from the policy, labelled by the gold preference
    ppo-gold         PPO with the gold reward instead of the reward model (`ppo.reward=gold`)
  The verdict ("DPO is simpler", "DPO is more stable") compares dpo-offline with ppo-rm only.

Pipeline, through the public CLI only (`python -m posttrain STAGE --recipe ...`, one subprocess per run):
  1. base model + tokenizer, SFT, preference pairs (SFT samples ranked by the gold preference
     "length first, then quality"), reward model on those pairs: built once (the `rm` stage builds the chain)
     under runs/shared/ and linked into every run directory (nothing is rebuilt).
  2. Every arm x seed (`dpo.seed` / `ppo.seed`) is one run, runs/<arm>-seed<S>/; a finished run (eval.json and
     the same overrides) is reused unless --fresh.
  3. A report: markdown, PNG plots (gold win-rate, gold vs proxy reward, KL, against training progress,
     every arm and seed), and a JSON with every number shown, under --out.

Compute budget: every arm gets about the same number of sequence forward+backward passes. The DPO-trainer arms:
80 steps x 32 pairs x 2 sides = 5,120 sequences (dpo-online-gold also samples 7 regenerations of 160 x 8
completions, at steps 10, 20, ..., 70); PPO: 20 iterations x 64 rollouts x 2 epochs x 2 models (policy, value)
= 5,120 sequences (+ 20 x 64 samples). Measured wall times are reported next to the results.

CPU:  python scripts/reproduce_e6.py --quick      tiny preset (~1.2M parameters), all seven arms x 3 seeds: 20.4 min
                                                   with --threads 2 on 2 idle CPU cores (docs/results-archive.md, E6)
      python scripts/reproduce_e6.py --quick --arms dpo-offline ppo-rm    the headline arms only (about the
                                                   two-arm time)
      python scripts/reproduce_e6.py --threads 2  small preset (~11M parameters, the seed's 10M+), all seven arms x 3
                                                   seeds: 96.2 min on 2 idle cores (AMD EPYC Zen 4; --estimate said
                                                   80 min at 2 threads, 127 at 1; RESULTS.md, E6)
      python scripts/reproduce_e6.py --estimate   times a few steps of every stage on `small`, prints the estimate
                                                   for the chosen --arms and --seeds
      Measured runtimes and results, with their machine and commit: RESULTS.md (E6).
Multi-GPU: every stage accepts `accelerate launch`, PPO too (it shards rollouts by prompt and gathers them; see
           "Several processes" in posttrain/trainers/ppo.py); this script runs every stage as one process, one
           after the other.
Options: --out DIR (default runs/e6 or runs/e6-quick), --seeds 0 1 2, --arms NAME ... (default: all seven; also
         comma-separated), --threads N (torch threads per run; 0 = torch's default), --fresh (redo runs whose
         results exist; by default finished runs are reused; with a subset of --arms only those arms' runs).
"""
from __future__ import annotations

import argparse
import ast
import io
import json
import math
import os
import shutil
import statistics
import sys
import time
import tokenize
from pathlib import Path
from typing import NamedTuple

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from posttrain.config import load_recipe  # noqa: E402
from posttrain.runtime import cpu_model  # noqa: E402
from stage_runner import run_stage  # noqa: E402  (scripts/, this file's folder)


class Arm(NamedTuple):
    stage: str  # the posttrain stage that trains it: dpo or ppo
    overrides: tuple[str, ...]  # CLI overrides on top of the E6 recipe (the seed is added per run)
    label: str  # what it is, for the report
    group: str  # LIKE or ORACLE


LIKE, ORACLE = "like with like", "oracle"
GROUPS = (LIKE, ORACLE)
# Like with like first: the headline. Without dpo.train_file, DPO (every loss type) trains on the prefs stage's
# train.jsonl, the same file the rm stage trains the reward model on (preferences.training_pairs in both), and
# both stop on a bad row (on_bad_rows=error) instead of dropping it: the same pairs.
ARMS: dict[str, Arm] = {
    "dpo-offline": Arm("dpo", ("dpo.online=false",),
                       "DPO on the reward model's preference pairs (offline)", LIKE),
    "ppo-rm": Arm("ppo", ("ppo.reward=rm",), "PPO against the reward model trained on those pairs", LIKE),
    "simpo-offline": Arm("dpo", ("dpo.online=false", "dpo.loss_type=simpo", "dpo.beta=2.0", "dpo.simpo_gamma=0.5"),
                         "SimPO (reference-free) on the reward model's pairs", LIKE),
    "orpo-offline": Arm("dpo", ("dpo.online=false", "dpo.loss_type=orpo", "dpo.beta=0.1"),
                        "ORPO (reference-free, with SFT loss) on the reward model's pairs", LIKE),
    "kto-offline": Arm("dpo", ("dpo.online=false", "dpo.loss_type=kto", "dpo.beta=0.1"),
                       "KTO on the reward model's pairs, unpaired (chosen: desirable, rejected: undesirable)", LIKE),
    "dpo-online-gold": Arm("dpo", ("dpo.online=true", "dpo.online_labeler=gold"),
                           "online DPO, pairs from the policy labelled by the gold preference (the recipe's)", ORACLE),
    "ppo-gold": Arm("ppo", ("ppo.reward=gold",), "PPO with the gold reward instead of the reward model", ORACLE),
}
HEADLINE = ("dpo-offline", "ppo-rm")  # the verdict compares these two only
ORACLE_PAIR = ("dpo-online-gold", "ppo-gold")
COLORS = {"dpo-offline": "tab:blue", "ppo-rm": "tab:red", "simpo-offline": "tab:green", "orpo-offline": "tab:purple",
          "kto-offline": "tab:brown",
          "dpo-online-gold": "tab:cyan", "ppo-gold": "tab:orange"}

# Settings on top of the shipped tiny-summarize recipe. Quick: the recipe as shipped (its numbers were
# tuned on `tiny`) with SFT pinned at 800 steps. Full: `small` with a lower SFT learning rate (6 layers, d=384).
# SFT stays at the 800 steps the E6 figures in RESULTS.md were measured with: the recipe's SFT now runs 2400
# (a far better and steadier SFT model), which leaves DPO and PPO less to improve and would triple E6's SFT time.
MODE = {
    "quick": {"model": {"path": "tiny"}, "sft": {"max_steps": 800}},
    "full": {"model": {"path": "small"}, "sft": {"lr": 1.0e-3, "max_steps": 800}},
}
# `--estimate --threads 1` on this machine (2 cores shared with other jobs, load average ~3-5), measured for the
# two-arm version (online DPO and PPO against the RM): wall seconds of sft 20 steps 36 (26 in the loop), prefs
# 100 prompts 16, rm 10 steps 112 (101 in the loop), dpo 10 steps with 2 regenerations 65, ppo 2 iterations 50
# (20 s per iteration). Scaled to the recipe's steps and 3 seeds, +10% for evaluation: 88 min on one thread for
# two arms. Six arms, counting every DPO-trainer arm at online DPO's time (an upper bound: offline DPO samples
# no pairs) and ppo-gold at PPO's: 201 min. The 2-thread speed-up (1.6x) is assumed, not measured here.
ESTIMATE = {"total_1thread_min": 88, "speedup_2threads": 1.6, "total_2threads_min": 55,
            "six_arms_1thread_min_upper_bound": 201}

# Config fields that are plumbing, not algorithm hyperparameters: files, logging, evaluation, checkpoints, and
# DPO's speed/memory switches that give the same numbers (reference precomputed or live, prompt sharing).
PLUMBING = {"train_file", "eval_file", "log_every", "eval_every", "eval_rows", "eval_pairs", "save_every",
            "keep_checkpoints", "final_eval_rows", "seed", "resume", "on_bad_rows", "proxy_rm", "reward_model",
            "max_new_tokens", "micro_batch_size", "reference", "share_prompt"}
# Models held in memory while training, per arm, from the trainers (evaluation's proxy RM excluded).
MODELS_IN_MEMORY = {
    "dpo-offline": (1, "the policy; the reference's log-probs of the pairs are precomputed before training "
                       "(trainers/dpo.py); the KL evaluation loads the SFT model for a moment"),
    "simpo-offline": (1, "the policy only: a reference-free loss, no reference log-probs at all (the KL evaluation "
                         "loads the SFT model for a moment)"),
    "orpo-offline": (1, "the policy only: a reference-free loss, no reference log-probs at all (the KL evaluation "
                        "loads the SFT model for a moment)"),
    "kto-offline": (1, "the policy; the reference's log-probs of every row and of its KL partner are precomputed "
                       "before training (trainers/dpo.py); the KL evaluation loads the SFT model for a moment"),
    "dpo-online-gold": (1, "the policy; reference log-probs precomputed; the reference is loaded for a moment at "
                           "each pair regeneration (peak 2)"),
    "ppo-rm": (4, "policy, value model, frozen reference, reward model (trainers/ppo.py)"),
    "ppo-gold": (3, "policy, value model (initialised from the reward model), frozen reference; the gold reward is "
                    "a function, not a model"),
}
FINAL_KEYS = ("win_rate", "gold_reward", "mean_quality", "frac_in_band", "kl", "proxy_reward")
FALL_TOL = 0.01  # monotonicity: a fall of at most this much between consecutive evaluations counts as flat


def arms_in(results: dict) -> list[str]:
    """The arms of `results` that have runs, like with like first, then oracle (ARMS order within a group)."""
    have = [a for a in ARMS if results["runs"].get(a)]
    return sorted(have, key=lambda a: GROUPS.index(ARMS[a].group))


def parse_arms(values: list[str] | None) -> list[str]:
    """--arms: names (space- or comma-separated), deduplicated, in ARMS order; an unknown name stops with the list."""
    names = [n.strip() for v in (values or list(ARMS)) for n in v.split(",") if n.strip()]
    unknown = [n for n in names if n not in ARMS]
    if unknown:
        raise ValueError(f"unknown arm{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}; "
                         f"choose from: {', '.join(ARMS)}")
    if not names:
        raise ValueError(f"--arms names no arm; choose from: {', '.join(ARMS)}")
    return [a for a in ARMS if a in names]


# ----------------------------------------------------------------------------- running stages
def posttrain(stage: str, recipe: Path, output_dir: Path, threads: int, log: Path, *overrides: str) -> float:
    """Run `python -m posttrain STAGE` as a user would; returns the wall time; raises with the log's tail."""
    took = run_stage([stage, "--recipe", str(recipe), f"run.output_dir={output_dir}", f"run.threads={threads}",
                      "run.quiet=true", *overrides], log, threads, "reproduce_e6")
    print(f"[e6] posttrain {stage} {' '.join(overrides)}: {took:.0f}s", flush=True)
    return took


def write_recipe(out: Path, mode: str) -> Path:
    """The shipped tiny-summarize recipe with this mode's settings, as out/e6-<mode>.yaml."""
    _, raw = load_recipe("tiny-summarize")
    for section, values in MODE[mode].items():
        raw.setdefault(section, {})
        raw[section] = {**(raw[section] or {}), **values}
    path = out / f"e6-{mode}.yaml"
    header = f"# E6 {mode}: tiny-summarize with {json.dumps(MODE[mode])}\n"
    path.write_text(header + yaml.safe_dump(raw, sort_keys=False))
    return path


def link_shared(shared_root: Path, seed_root: Path) -> None:
    """Point a seed's run directory at the shared SFT model, pairs and reward model (nothing is rebuilt)."""
    for stage in ("sft", "prefs", "rm"):
        dst = seed_root / stage / "final"
        if not dst.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to((shared_root / stage / "final").resolve(), target_is_directory=True)


# ----------------------------------------------------------------------------- numbers
def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(l) for l in path.read_text().splitlines() if l.strip()] if path.is_file() else []


def code_lines(path: Path) -> int:
    """Lines of code: not blank, not only a comment, not part of a docstring."""
    src = path.read_text()
    doc_lines: set[int] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(getattr(first.value, "value", None), str):
                doc_lines.update(range(first.lineno, first.end_lineno + 1))
        if isinstance(node, ast.ClassDef):  # field doc strings under dataclass fields
            for a, b in zip(node.body, node.body[1:]):
                if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant):
                    doc_lines.update(range(b.lineno, b.end_lineno + 1))
    code: set[int] = set()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
                            tokenize.ENDMARKER):
            code.update(range(tok.start[0], tok.end[0] + 1))
    return len(code - doc_lines)


def hyperparameters(stage: str) -> list[str]:
    import dataclasses

    from posttrain.cli import STAGES

    cfg_cls, _ = STAGES[stage].load()
    return [f.name for f in dataclasses.fields(cfg_cls) if f.name not in PLUMBING]


def mean_std(xs: list[float]) -> tuple[float, float]:
    xs = [x for x in xs if x is not None and not math.isnan(x)]
    if not xs:
        return float("nan"), float("nan")
    return statistics.fmean(xs), (statistics.stdev(xs) if len(xs) > 1 else 0.0)


# Stability of one run, on its gold-reward curve. The step-0 evaluation (the SFT model itself, before any update)
# is left out of all three: a policy's first update moves it far from there, up or down, and a measure from the
# running best that starts at step 0 is dominated by that first move instead of by how steady training is.
def after_start(curve: dict, key: str = "gold/reward") -> list[float]:
    """The curve's values at the evaluations after step 0 (missing values dropped)."""
    ys, steps = list(curve.get(key, [])), list(curve.get("step", []))
    if steps and steps[0] == 0:
        ys = ys[1:]
    return [y for y in ys if y is not None and not math.isnan(y)]


def give_back(ys: list[float]) -> float:
    """How much of its own peak a run loses by the end: the best value minus the final one (0: it ends at its best)."""
    return max(ys) - ys[-1] if ys else float("nan")


def worst_fall(ys: list[float]) -> float:
    """The largest fall between two consecutive evaluations (0 for a curve that never falls)."""
    pairs = list(zip(ys, ys[1:]))
    return max(0.0, max(a - b for a, b in pairs)) if pairs else float("nan")


def monotonicity(ys: list[float], tol: float = FALL_TOL) -> float:
    """Fraction of consecutive evaluations where the value did not drop by more than tol."""
    pairs = list(zip(ys, ys[1:]))
    return sum(b >= a - tol for a, b in pairs) / len(pairs) if pairs else float("nan")


def stability(curve: dict) -> dict[str, float]:
    """give_back, monotonicity and worst_fall of a run's gold reward over the evaluations after step 0."""
    ys = after_start(curve)
    return {"give_back": give_back(ys), "monotonicity": monotonicity(ys), "worst_fall": worst_fall(ys),
            "evaluations": len(ys)}


def curves(run_dir: Path, max_steps: int) -> dict[str, list[float]]:
    rows = [r for r in read_jsonl(run_dir / "metrics.jsonl") if "gold/reward" in r]
    out: dict[str, list[float]] = {"progress": [r["step"] / max_steps for r in rows], "step": [r["step"] for r in rows]}
    for key in ("gold/win_rate", "gold/reward", "gold/quality", "gold/in_band", "proxy/reward", "kl"):
        out[key] = [r.get(key, float("nan")) for r in rows]
    return out


# ----------------------------------------------------------------------------- plots
def plot(results: dict, out: Path) -> list[str]:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    arms = arms_in(results)
    if not arms:
        return []
    files = []

    def line(arm: str) -> str:
        return "--" if ARMS[arm].group == ORACLE else "-"

    def panel(ax, key, ylabel, first=0):
        """Every seed thin, the mean thick (oracle arms dashed); `first` = 1 leaves out the step-0 (SFT) point."""
        for arm in arms:
            runs, color = results["runs"][arm], COLORS.get(arm, "tab:gray")
            same = all(len(r["curves"][key]) == len(runs[0]["curves"][key]) for r in runs)
            for i, run in enumerate(runs):
                c = run["curves"]
                ax.plot(c["progress"][first:], c[key][first:], marker="o", ms=2.5, ls=line(arm), color=color,
                        alpha=0.3, lw=0.8, label=f"{arm} (each seed)" if i == 0 and not same else None)
            if same:
                mean = [statistics.fmean(vals) for vals in zip(*(r["curves"][key] for r in runs))]
                ax.plot(runs[0]["curves"]["progress"][first:], mean[first:], ls=line(arm), color=color, lw=2.2,
                        label=f"{arm} (mean of {len(runs)} seeds)")
        ax.set_xlabel("fraction of the training budget")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)

    title = f"E6 ({results['model']['preset']}, {results['model']['parameters'] / 1e6:.1f}M params)"
    for name, key, ylabel in (("win_rate.png", "gold/win_rate", "gold win-rate vs the SFT model"),
                              ("kl.png", "kl", "KL(policy || SFT), nats per sequence")):
        fig, ax = plt.subplots(figsize=(7.5, 4.5))
        panel(ax, key, ylabel)
        ax.set_title(f"{title}: {ylabel} (dashed: oracle arms)", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        files.append(name)

    # The step-0 point (the SFT model itself) is far below the rest; it is left out and given in the title.
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    panel(axes[0], "gold/reward", "gold reward", first=1)
    panel(axes[1], "proxy/reward", "proxy (reward model) reward", first=1)
    for arm in arms:  # gold against proxy: the over-optimisation picture (Gao et al. 2022)
        color = COLORS.get(arm, "tab:gray")
        for i, run in enumerate(results["runs"][arm]):
            c = run["curves"]
            axes[2].plot(c["proxy/reward"][1:], c["gold/reward"][1:], marker="o", ms=2.5, ls=line(arm), color=color,
                         alpha=0.5, label=arm if i == 0 else None)
            axes[2].plot(c["proxy/reward"][-1:], c["gold/reward"][-1:], "*", ms=11, color=color)
    axes[2].set_xlabel("proxy (reward model) reward (star: end of training)")
    axes[2].set_ylabel("gold reward")
    axes[2].grid(alpha=0.3)
    axes[2].legend(fontsize=7)
    c0 = results["runs"][arms[0]][0]["curves"]
    sft_note = (f"; SFT model (step 0, not drawn): gold {c0['gold/reward'][0]:.2f}, proxy {c0['proxy/reward'][0]:.2f}"
                if c0["step"] and c0["step"][0] == 0 else "")
    fig.suptitle(f"E6: gold vs proxy reward over training, every arm and seed (dashed: oracle arms){sft_note}",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(out / "gold_vs_proxy.png", dpi=100)
    plt.close(fig)
    files.append("gold_vs_proxy.png")
    return files


# ----------------------------------------------------------------------------- report
def fmt(m: float, s: float | None = None, d: int = 3) -> str:
    if m is None or (isinstance(m, float) and math.isnan(m)):
        return "n/a"
    return f"{m:.{d}f}" if s is None or (isinstance(s, float) and math.isnan(s)) else f"{m:.{d}f} ± {s:.{d}f}"


def analyse(results: dict) -> dict:
    """Per arm: finals (mean, std over seeds), stability (see `stability`); per trainer: simplicity; the claims
    (dpo-offline vs ppo-rm) when both ran, else None."""
    arms = arms_in(results)
    summary: dict = {}
    for arm in arms:
        runs = results["runs"][arm]
        finals = [r["final"] for r in runs]
        s = {k: mean_std([f.get(k) for f in finals]) for k in FINAL_KEYS}
        s["per_seed_win_rate"] = [f.get("win_rate") for f in finals]
        stab = [stability(r["curves"]) for r in runs]
        for k in ("give_back", "monotonicity", "worst_fall"):
            s[k] = mean_std([x[k] for x in stab])
            s[f"per_seed_{k}"] = [x[k] for x in stab]
        s["evaluations_after_step0"] = [x["evaluations"] for x in stab]
        s["train_seconds"] = mean_std([r["seconds"] for r in runs])
        summary[arm] = s
    stages = [st for st in ("dpo", "ppo") if any(ARMS[a].stage == st for a in arms)]
    simp: dict = {st: {"hyperparameters": hyperparameters(st),
                       "code_lines": code_lines(ROOT / "posttrain" / "trainers" / f"{st}.py")} for st in stages}
    if "ppo" in simp:  # PPO also needs the reward model trained (trainers/reward.py), its value model starts there
        simp["ppo"]["code_lines_with_prerequisites"] = simp["ppo"]["code_lines"] + code_lines(
            ROOT / "posttrain" / "trainers" / "reward.py")
        simp["ppo"]["reward_model_hyperparameters"] = hyperparameters("rm")
    if "dpo" in simp:
        simp["dpo"]["code_lines_with_prerequisites"] = simp["dpo"]["code_lines"]
        simp["dpo"]["online_only"] = [h for h in simp["dpo"]["hyperparameters"] if h.startswith("online")]
    models = {arm: {"models_in_memory": MODELS_IN_MEMORY[arm][0], "models_note": MODELS_IN_MEMORY[arm][1]}
              for arm in arms}
    claims = None
    if all(a in summary for a in HEADLINE):
        d, p = (simp[ARMS[a].stage] for a in HEADLINE)
        md, mp = (models[a]["models_in_memory"] for a in HEADLINE)
        sd, sp = (summary[a] for a in HEADLINE)
        claims = {
            "dpo_simpler": {"hyperparameters": len(d["hyperparameters"]) < len(p["hyperparameters"]),
                            "code_lines": d["code_lines"] < p["code_lines"], "models_in_memory": md < mp},
            "dpo_more_stable": {"spread_of_final_win_rate": sd["win_rate"][1] < sp["win_rate"][1],
                                "spread_of_final_gold_reward": sd["gold_reward"][1] < sp["gold_reward"][1],
                                "give_back": sd["give_back"][0] <= sp["give_back"][0],
                                "monotonicity": sd["monotonicity"][0] >= sp["monotonicity"][0],
                                "worst_fall": sd["worst_fall"][0] <= sp["worst_fall"][0]},
            "compared": list(HEADLINE)}
    return {"summary": summary, "simplicity": simp, "models_in_memory": models, "claims": claims}


def verdict(flags: dict[str, bool]) -> str:
    n = sum(flags.values())
    return "holds" if n == len(flags) else ("does not hold" if n == 0 else f"partly holds ({n} of {len(flags)})")


STABILITY_TEXT = (
    "How stability is measured, on each run's gold-reward curve (the held-out evaluations during training): "
    "(a) **spread**: the standard deviation over seeds of the final gold win-rate and of the final gold reward; "
    "(b) **give-back**: the best gold reward over the evaluations after step 0 minus the final one, i.e. how much "
    "of its own peak a run loses by the end (0: it ends at its best); "
    "(c) **monotonicity**: the fraction of consecutive evaluations after step 0 where the gold reward did not fall "
    f"by more than {FALL_TOL}; "
    "(d) **worst fall**: the largest fall of the gold reward between two consecutive evaluations after step 0 "
    "(0: it never falls). (b)-(d) are mean ± std over seeds. Step 0 is the SFT model itself, before any update; it "
    "is left out of (b)-(d) because a run's first move away from it, up or down, says little about how steady "
    "training is. (Earlier versions reported a max drawdown from the running best starting at step 0: one seed's "
    "early dip at its first evaluation decided that number on its own, so it is no longer used.)")


def report_md(results: dict, an: dict, plots: list[str]) -> str:
    m = results["model"]
    s, simp, models, claims = an["summary"], an["simplicity"], an["models_in_memory"], an["claims"]
    arms = [a for a in arms_in(results) if a in s]

    def name(a: str) -> str:
        return f"`{a}`" + (" (oracle)" if ARMS[a].group == ORACLE else "")

    L = [f"# E6 reproduction: DPO vs PPO-for-RLHF on tiny-summarize ({results['mode']} mode)", "",
         f"Model: `{m['preset']}` preset, **{m['parameters'] / 1e6:.2f}M parameters** ({m['parameters']:,}), "
         f"built from scratch; SFT, preference pairs and reward model built once and shared by every run; seeds "
         f"{results['seeds']} for each arm. Threads per run: {results['threads'] or 'torch default'}. Wall time of "
         f"the pipeline (every run, one after the other): {results['pipeline_seconds'] / 60:.1f} min; this "
         f"invocation {results['total_seconds'] / 60:.1f} min (finished runs are reused). Machine: "
         f"{cpu_model()}, {os.cpu_count()} cores; load average at the end {results['load_end']} (other jobs "
         f"running beside the pipeline slow its runs and inflate the times).", "",
         f"SFT model (held-out, greedy): gold quality {fmt(results['sft'].get('mean_quality'))}, in band "
         f"{fmt(results['sft'].get('frac_in_band'), d=2)}. Reward model held-out pair accuracy "
         f"{fmt(results['rm'].get('eval/accuracy'))}.", "",
         "Shared stage times: " + ", ".join(f"{k} {v:.0f}s" for k, v in results["shared_seconds"].items()) + ".", "",
         "## Arms", "",
         "The seed's claim is about the same preference data, so the headline arms (**like with like**) all learn "
         "from exactly the preference pairs the reward model was trained on (the prefs stage's `train.jsonl`): "
         "offline DPO, SimPO and ORPO on those pairs, and PPO against the reward model trained on them. The "
         "**oracle** arms use the gold preference or the gold reward directly; they are not the seed's setting "
         "and are shown as a reference only.", "",
         "| arm | setting | trainer | overrides | what it is |", "|---|---|---|---|---|"]
    for a in arms:
        arm = ARMS[a]
        L.append(f"| `{a}` | {arm.group} | {arm.stage} | `{' '.join(arm.overrides) or '(recipe)'}` | {arm.label} |")
    L += ["", "## Final policies (200 held-out prompts, greedy; mean ± std over seeds)", "",
          "| arm | setting | gold win-rate vs SFT | per seed | gold reward | gold quality | in band | KL to SFT (nats) "
          "| proxy RM reward | train time (s) |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for arm in arms:
        a = s[arm]
        L.append(f"| `{arm}` | {ARMS[arm].group} | {fmt(*a['win_rate'])} | "
                 f"{', '.join(fmt(x) for x in a['per_seed_win_rate'])} | {fmt(*a['gold_reward'])} | "
                 f"{fmt(*a['mean_quality'])} | {fmt(*a['frac_in_band'], d=2)} | {fmt(*a['kl'], d=2)} | "
                 f"{fmt(*a['proxy_reward'])} | {fmt(*a['train_seconds'], d=0)} |")
    L += ["", "Win-rate: the gold preference (length band first, then quality) of the policy's summary against the "
          "SFT model's, ties count half. Gold reward = quality - 2 x words outside the length band.", "",
          "## Stability (over training, gold reward on 100 held-out prompts at each evaluation)", "",
          "| arm | setting | spread of final win-rate (std) | spread of final gold reward (std) | give-back "
          "| monotonicity | worst fall | evaluations after step 0 |",
          "|---|---|---|---|---|---|---|---|"]
    for arm in arms:
        a = s[arm]
        n_ev = sorted(set(a["evaluations_after_step0"]))
        L.append(f"| `{arm}` | {ARMS[arm].group} | {fmt(a['win_rate'][1])} | {fmt(a['gold_reward'][1])} | "
                 f"{fmt(*a['give_back'])} | {fmt(*a['monotonicity'], d=2)} | {fmt(*a['worst_fall'])} | "
                 f"{', '.join(map(str, n_ev))} |")
    L += ["", STABILITY_TEXT, "", "## Simplicity", "",
          "| arm | trainer | hyperparameters | trainer code lines | + prerequisites "
          "| models in memory while training |",
          "|---|---|---|---|---|---|"]
    for arm in arms:
        st = simp[ARMS[arm].stage]
        L.append(f"| `{arm}` | {ARMS[arm].stage} | {len(st['hyperparameters'])} | {st['code_lines']} | "
                 f"{st['code_lines_with_prerequisites']} | {models[arm]['models_in_memory']}: "
                 f"{models[arm]['models_note']} |")
    L += ["", "Hyperparameters and code lines are the trainer's (one DPO trainer runs DPO, SimPO, ORPO and KTO; one PPO "
          "trainer runs both PPO arms). Hyperparameters: fields of the stage config minus plumbing (files, logging, "
          "evaluation, checkpoints, seed). Code lines: non-blank, non-comment, non-docstring lines of "
          "`posttrain/trainers/<trainer>.py`; PPO's prerequisites add the reward-model trainer "
          "(`trainers/reward.py`): PPO's reward and its value model's initialisation come from it.", ""]
    if "dpo" in simp:
        L += ["DPO trainer hyperparameters: " + ", ".join(simp["dpo"]["hyperparameters"])
              + f" ({len(simp['dpo']['online_only'])} of them, " + ", ".join(simp["dpo"]["online_only"])
              + ", are the online mode's switch and settings: unused by the offline arms)", ""]
    if "ppo" in simp:
        L += ["PPO trainer hyperparameters: " + ", ".join(simp["ppo"]["hyperparameters"]) + " (plus the reward "
              f"model's own {len(simp['ppo']['reward_model_hyperparameters'])}: "
              + ", ".join(simp["ppo"]["reward_model_hyperparameters"]) + "; the DPO arms use the same reward model "
              "only for the proxy curve)", ""]
    L += ["## Does the seed's claim hold here? (like with like: `dpo-offline` vs `ppo-rm`)", ""]
    if claims is None:
        L.append(f"- Not judged: the verdict compares `{HEADLINE[0]}` with `{HEADLINE[1]}` and this run had "
                 f"{', '.join(f'`{a}`' for a in arms) or 'no arm'} (`--arms`).")
    else:
        d, p = s["dpo-offline"], s["ppo-rm"]
        sd, sp = simp["dpo"], simp["ppo"]
        md, mp = models["dpo-offline"]["models_in_memory"], models["ppo-rm"]["models_in_memory"]
        L.append(f"- **DPO is simpler: {verdict(claims['dpo_simpler'])}** (`dpo-offline` vs `ppo-rm`). "
                 f"{len(sd['hyperparameters'])} vs {len(sp['hyperparameters'])} hyperparameters, {sd['code_lines']} "
                 f"vs {sp['code_lines']} trainer code lines, {md} vs {mp} models in memory.")
        L.append(f"- **DPO is more stable: {verdict(claims['dpo_more_stable'])}** (`dpo-offline` vs `ppo-rm`). "
                 f"Spread of the final win-rate across seeds {fmt(d['win_rate'][1])} vs {fmt(p['win_rate'][1])}; "
                 f"spread of the final gold reward {fmt(d['gold_reward'][1])} vs {fmt(p['gold_reward'][1])}; "
                 f"give-back {fmt(d['give_back'][0])} vs {fmt(p['give_back'][0])}; monotonicity "
                 f"{fmt(d['monotonicity'][0], d=2)} vs {fmt(p['monotonicity'][0], d=2)}; worst fall "
                 f"{fmt(d['worst_fall'][0])} vs {fmt(p['worst_fall'][0])}.")
        better = "`dpo-offline`" if d["win_rate"][0] > p["win_rate"][0] else "`ppo-rm`"
        L.append(f"- Final quality: {better} has the higher mean gold win-rate against SFT ({fmt(d['win_rate'][0])} "
                 f"`dpo-offline` vs {fmt(p['win_rate'][0])} `ppo-rm`); KL to the SFT model {fmt(d['kl'][0], d=2)} "
                 f"vs {fmt(p['kl'][0], d=2)} nats.")
        if p["proxy_reward"][0] > d["proxy_reward"][0] and p["gold_reward"][0] < d["gold_reward"][0]:
            L.append(f"- Over-optimisation: `ppo-rm` ends with the higher proxy (reward-model) reward "
                     f"({fmt(p['proxy_reward'][0])} vs {fmt(d['proxy_reward'][0])} `dpo-offline`) but the lower gold "
                     f"reward ({fmt(p['gold_reward'][0])} vs {fmt(d['gold_reward'][0])}): it climbs the reward "
                     "model, errors included (Gao et al. 2022).")
    others = [a for a in ("simpo-offline", "orpo-offline", "kto-offline") if a in s]
    if others:
        ref = s.get("dpo-offline")
        L.append("- Other preference losses on the same pairs (not part of the verdict): " + "; ".join(
            f"`{a}` win-rate {fmt(*s[a]['win_rate'])}, give-back {fmt(s[a]['give_back'][0])}" for a in others)
            + (f" (`dpo-offline` {fmt(*ref['win_rate'])}, give-back {fmt(ref['give_back'][0])})." if ref else "."))
    L += ["", "## Oracle arms (gold labels / gold reward; not the seed's setting)", ""]
    if all(a in s for a in ORACLE_PAIR):
        d, p = s["dpo-online-gold"], s["ppo-gold"]
        L.append(f"With the gold preference itself as the labeler (`dpo-online-gold`, the recipe's online DPO) and "
                 f"the gold reward itself as PPO's reward (`ppo-gold`), neither is trained on the reward model's pairs "
                 f"or scores, so neither inherits their errors: gold win-rate {fmt(*d['win_rate'])} vs "
                 f"{fmt(*p['win_rate'])}, "
                 f"final gold reward {fmt(*d['gold_reward'])} vs {fmt(*p['gold_reward'])}, give-back "
                 f"{fmt(d['give_back'][0])} vs {fmt(p['give_back'][0])}, worst fall {fmt(d['worst_fall'][0])} vs "
                 f"{fmt(p['worst_fall'][0])}. Online DPO also samples fresh pairs from its own policy (7 "
                 "regenerations), which offline DPO does not: these arms show what each method reaches with a "
                 "perfect labeler, not the seed's comparison, and are not part of the verdict.")
    else:
        have = [a for a in ORACLE_PAIR if a in s]
        L.append("Not run as a pair (`--arms`)" + (f"; this run had {', '.join(f'`{a}`' for a in have)}, in the "
                                                   "tables above." if have else "."))
    L += ["", "Caveats: " + f"{len(results['seeds'])} seeds is a small sample (a spread is one number from "
          f"{len(results['seeds'])}); SimPO, ORPO and KTO run at one setting each (SimPO beta 2.0, gamma 0.5; ORPO "
          "lambda 0.1; KTO beta 0.1, both weights 1, on the pairs unpaired: as many desirable as undesirable rows) "
          "with DPO's learning rate, not tuned here; every arm shares one SFT model and one compute budget in sequence passes, "
          "not in wall time; the gold reward that the stability measures use is evaluated on 100 held-out prompts "
          "at a handful of evaluations per run (the count is in the stability table).", "", "## Plots", ""]
    L += [f"![{f}]({f})" for f in plots] or ["(matplotlib is not installed: no plots)"]
    if results.get("stage_plots"):
        L += ["", "Each run's own metric plots (loss, reward, KL, lengths, ...: `posttrain plot`, the same function): "
              + ", ".join(f"[{name}]({folder})" for name, folder in results["stage_plots"].items()) + "."]
    L += ["", f"Every number above is in `e6_results.json`; the runs are under `{results['runs_dir']}`."]
    return "\n".join(L) + "\n"


# ----------------------------------------------------------------------------- main
def estimate(out: Path, threads: int, arms: list[str], seeds: int = 3) -> dict:
    """Time a few steps of each stage on `small` and extrapolate the full mode (`seeds` seeds of every arm).

    Per-step times come from the stages' metrics.jsonl; startup, the reference precompute, online
    regenerations (every 5 steps here, every 10 in the recipe: an overestimate) are inside the DPO and
    PPO wall times, which are scaled by steps. Offline DPO is timed on its own (no regenerations); SimPO
    and ORPO are counted at its time (they skip the reference precompute: a slight overestimate), ppo-gold
    at PPO's (the gold scorer is cheaper than the reward model). Evaluation is not timed here: +10% is added."""
    recipe = write_recipe(out, "full")
    full = yaml.safe_load(recipe.read_text())
    root = out / "estimate"
    logs = out / "logs"
    dpo_args = ("max_steps=10", "eval_every=0", "final_eval_rows=0")
    stages = {ARMS[a].stage for a in arms}
    wall = {
        "sft": posttrain("sft", recipe, root, threads, logs / "est_sft.log", "max_steps=20", "eval_every=0",
                         "save_every=0", "final_eval_rows=0"),
        "prefs": posttrain("prefs", recipe, root, threads, logs / "est_prefs.log", "n_prompts=100",
                           "n_eval_prompts=20"),
        "rm": posttrain("rm", recipe, root, threads, logs / "est_rm.log", "max_steps=10"),
    }
    if any(a != "dpo-online-gold" and ARMS[a].stage == "dpo" for a in arms):
        wall["dpo offline"] = posttrain("dpo", recipe, root, threads, logs / "est_dpo_offline.log", *dpo_args,
                                        "online=false")
    if "dpo-online-gold" in arms:
        wall["dpo online"] = posttrain("dpo", recipe, root, threads, logs / "est_dpo.log", *dpo_args, "online=true",
                                       "online_every=5")
    if "ppo" in stages:
        wall["ppo"] = posttrain("ppo", recipe, root, threads, logs / "est_ppo.log", "max_steps=2", "eval_every=0",
                                "final_eval_rows=0", "reward_norm_prompts=32")
    last = {st: read_jsonl(root / recipe.stem / st / "metrics.jsonl")[-1]["time"] for st in ("sft", "rm")}
    parts = {
        "sft": last["sft"] / 20 * full["sft"]["max_steps"],
        "prefs": wall["prefs"] * full["prefs"]["n_prompts"] / 100,
        "rm": last["rm"] / 10 * full["rm"]["max_steps"],
    }
    for a in arms:
        stage = ARMS[a].stage
        key = "ppo" if stage == "ppo" else ("dpo online" if a == "dpo-online-gold" else "dpo offline")
        per_run = wall[key] * full[stage]["max_steps"] / (2 if stage == "ppo" else 10)
        parts[f"{a} ({seeds} seeds)"] = seeds * per_run
    total = 1.1 * sum(parts.values())
    est = {"arms": arms, "seeds": seeds, "measured_wall_s": wall, "extrapolated_s": parts,
           "total_1thread_min": total / 60, "total_2threads_min": total / 60 / ESTIMATE["speedup_2threads"],
           "threads": threads, "load": " ".join(f"{x:.2f}" for x in os.getloadavg())}
    (out / "estimate.json").write_text(json.dumps(est, indent=2))
    print(json.dumps(est, indent=2))
    return est


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the same pipeline on the tiny preset")
    ap.add_argument("--estimate", action="store_true", help="time a few steps of each stage on `small` and stop")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default runs/e6 or runs/e6-quick)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--arms", nargs="+", default=None, metavar="ARM",
                    help=f"arms to run (space- or comma-separated; default: all): {', '.join(ARMS)}. The verdict "
                         f"needs {HEADLINE[0]} and {HEADLINE[1]}")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per run (0: torch's default)")
    ap.add_argument("--fresh", action="store_true", help="redo runs whose results already exist (all of --out with "
                    "every arm; with a subset of --arms only those arms' runs)")
    args = ap.parse_args(argv)
    try:
        args.arms = parse_arms(args.arms)
    except ValueError as e:
        ap.error(f"--arms: {e}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    mode = "quick" if args.quick else "full"
    out = (args.out or ROOT / "runs" / ("e6-quick" if args.quick else "e6")).resolve()
    if args.fresh and out.exists():
        if args.arms == list(ARMS):  # everything, the shared SFT / pairs / RM too
            shutil.rmtree(out)
        else:  # a subset: only its runs; the other arms' runs and the shared models stay
            for arm in args.arms:
                for seed_root in (out / "runs").glob(f"{arm}-seed*"):
                    shutil.rmtree(seed_root)
    out.mkdir(parents=True, exist_ok=True)
    if args.estimate:
        estimate(out, args.threads, args.arms, len(args.seeds))
        return 0
    t_all = time.time()
    recipe = write_recipe(out, mode)
    name = recipe.stem
    cfg = yaml.safe_load(recipe.read_text())
    shared = out / "runs" / "shared"
    shared_seconds: dict[str, float] = {}
    shared_timing = shared / "e6_seconds.json"
    if not (shared / name / "rm" / "final").exists() or not shared_timing.is_file():  # rm builds base, SFT, pairs
        took = posttrain("rm", recipe, shared, args.threads, out / "logs" / "shared.log")
        shared_timing.write_text(json.dumps({"seconds": took}))
    else:
        print(f"[e6] reusing the shared SFT model, pairs and reward model in {shared / name}")
    shared_seconds["base+sft+prefs+rm"] = json.loads(shared_timing.read_text())["seconds"]
    for stage in ("sft", "rm"):  # the training loops' own times, from their metrics
        rows = read_jsonl(shared / name / stage / "metrics.jsonl")
        if rows:
            shared_seconds[f"{stage} loop"] = rows[-1].get("time", 0.0)

    import transformers

    from posttrain.models import count_parameters, load_model

    transformers.utils.logging.disable_progress_bar()
    params = count_parameters(load_model(shared / name / "sft" / "final"))
    sft_json = shared / name / "sft" / "eval.json"
    sft_eval = json.loads(sft_json.read_text()) if sft_json.is_file() else {}
    rm_eval = json.loads((shared / name / "rm" / "eval.json").read_text()).get("heldout", {})
    results: dict = {"mode": mode, "seeds": args.seeds, "threads": args.threads, "recipe": str(recipe),
                     "model": {"preset": cfg["model"]["path"], "parameters": params},
                     "sft": {k: v for k, v in sft_eval.get("sft", {}).items() if not k.startswith("_")},
                     "rm": rm_eval, "shared_seconds": shared_seconds, "runs_dir": str(out / "runs"),
                     "arm_table": {a: ARMS[a]._asdict() for a in args.arms},
                     "runs": {a: [] for a in args.arms}}
    from posttrain.cli import STAGES

    for arm_name in args.arms:
        arm = ARMS[arm_name]
        stage = arm.stage
        max_steps = cfg.get(stage, {}).get("max_steps") or getattr(STAGES[stage].load()[0](), "max_steps")
        for seed in args.seeds:
            seed_root = out / "runs" / f"{arm_name}-seed{seed}"
            run_dir = seed_root / name / stage
            link_shared(shared / name, seed_root / name)
            timing = run_dir / "e6_seconds.json"
            overrides = [*arm.overrides, f"{stage}.seed={seed}"]
            done = json.loads(timing.read_text()) if (run_dir / "eval.json").is_file() and timing.is_file() else None
            if done is not None and done.get("overrides") == overrides:
                seconds = done["seconds"]
                print(f"[e6] reusing {run_dir}")
            else:  # not run yet, or run with other settings (the stage keeps that run as <dir>.prev)
                seconds = posttrain(stage, recipe, seed_root, args.threads, out / "logs" / f"{arm_name}-seed{seed}.log",
                                    *overrides)
                timing.write_text(json.dumps({"seconds": seconds, "arm": arm_name, "overrides": overrides}))
            final = json.loads((run_dir / "eval.json").read_text()).get(stage, {})
            results["runs"][arm_name].append({"seed": seed, "seconds": seconds, "run_dir": str(run_dir),
                                              "final": final, "curves": curves(run_dir, max_steps)})
    results["total_seconds"] = time.time() - t_all  # this invocation (finished runs are reused, not redone)
    results["pipeline_seconds"] = shared_seconds["base+sft+prefs+rm"] + sum(
        r["seconds"] for a in args.arms for r in results["runs"][a])  # every run's wall time, however invoked
    results["load_end"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    an = analyse(results)
    results.update(an)
    plots = plot(results, out)
    from posttrain.plots import plot_runs  # `posttrain plot` of every run, linked from the report

    results["stage_plots"] = plot_runs({f"{a}-seed{r['seed']}": Path(r["run_dir"]) for a in args.arms
                                        for r in results["runs"][a]}, out, say=lambda m: print(f"[e6] {m}"))
    (out / "e6_results.json").write_text(json.dumps(results, indent=2, default=str))
    (out / "report.md").write_text(report_md(results, an, plots))
    print(f"[e6] report: {out / 'report.md'} (plots: {', '.join(plots) or 'none'}; numbers: {out / 'e6_results.json'})")
    if an["claims"] is None:
        print(f"[e6] no verdict: it compares {HEADLINE[0]} with {HEADLINE[1]}; --arms ran {', '.join(args.arms)}")
    else:
        print(f"[e6] {HEADLINE[0]} vs {HEADLINE[1]}: DPO simpler: {verdict(an['claims']['dpo_simpler'])}; DPO more "
              f"stable: {verdict(an['claims']['dpo_more_stable'])}")
    print(f"[e6] pipeline {results['pipeline_seconds'] / 60:.1f} min, this invocation "
          f"{results['total_seconds'] / 60:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
