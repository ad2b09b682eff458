"""E7 (seed §16): reasoning-RL on tiny-math -- GRPO against best-of-K and majority-vote sampling of the SFT model.

Pipeline, through the public CLI and API only:
  1. `python -m posttrain sft --recipe tiny-math`: tokenizer + tiny model from scratch, then SFT on worked
     digit-by-digit solutions, stopped on purpose at partial accuracy (see the recipe). Timed.
  2. Baselines without RL, on the same N held-out problems: greedy accuracy, and 16 samples per problem at
     temperature 1 from the rollout engine (`posttrain.rollout.generate`, n=16), scored by the math
     verifier in a worker pool (`posttrain.verifiers.runner.VerifierPool`). From them, for K in {1, 4, 16}:
     - pass@K: verifier-oracle best-of-K (some sample of K is right), the unbiased estimator of
       Chen et al. 2021 (1 - C(n-c, K) / C(n, K)); the whole curve K = 1..16 is computed too;
     - maj@K: majority vote over the verifier's normalised extracted answers (no answer = no vote; a
       tie at the top counts 1/ties when the right answer is among the tied), averaged over the 16/K
       disjoint groups of K samples.
     pass@K needs the reference at inference time (an oracle); maj@K does not.
  3. `python -m posttrain grpo --recipe tiny-math` from that SFT model, timed, with the training rollouts
     saved every few steps. Its metrics.jsonl gives the held-out greedy accuracy curve, the response
     length of training samples and of held-out greedy answers over training, and the tokens sampled.
  4. The same evaluation of the GRPO model (greedy, pass@K, maj@K), the frequency of verification and
     self-correction phrases before and after RL (held-out greedy answers and samples, and the saved
     training rollouts over steps), and the compute of each route: training time and tokens (SFT, GRPO)
     against inference samples and tokens per problem.
  5. Report under --out: report.md, PNG plots, e7.json (the data of every figure and table).

--model real: E7 as the seed states it ("take a small instruction-tuned LM"): the smol-math recipe on
  SmolLM2-135M-Instruct (`posttrain models fetch smollm2-135m-instruct models/smollm2-135m-instruct` first).
  Step 1 is skipped: the instruct model as it is is the starting point (model.start_from=base), prompted
  through its own chat template; the held-out set is word-math's (posttrain/tasks/wordmath.py); samples
  are drawn at the recipe's GRPO temperature; phrases counted are word-math's (verification, self-
  correction, re-computation lines), with examples; the report states the verdict against the +10-point
  target.

CPU:  python scripts/reproduce_e7.py            the shipped recipe; 15 min on 2 idle cores at 2 threads, ~25 min with --threads 1
      python scripts/reproduce_e7.py --quick    a smoke run of the same pipeline (short SFT and GRPO, 40
                                                held-out problems); a few minutes
      Measured runtimes and results, with their machine and commit: RESULTS.md (E7).
Multi-GPU: each stage accepts `accelerate launch`; this script runs them one process at a time.
      python scripts/reproduce_e7.py --model real [--quick]   see RESULTS.md (E7 on a real model) for its runtime
Options: --model tiny|real, --out DIR (default runs/e7[-real][-quick]), --threads N (torch threads per stage and for the
         evaluation here; 0 = torch's default), --eval-rows N, --fresh (redo everything; by default a
         finished SFT or GRPO run in --out is reused), any number of `--set stage.key=value` overrides
         passed to both CLI stages (e.g. --set grpo.max_steps=100).

Phrases counted (`posttrain.tasks.math.behaviour_counts`): verification = "check" (the SFT data teaches an
optional "Check: a+b=c" line in 25% of training solutions, so its frequency can move under RL);
self-correction = wait / redo / mistake / actually / let me / again (never in the SFT data).
"""
from __future__ import annotations

import argparse
import collections
import importlib
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stage_runner import prepare, run_stage  # noqa: E402  (scripts/, this file's folder)

KS = (1, 4, 16)  # samples per problem for best-of-K / majority vote
N_SAMPLES = max(KS)  # samples drawn per problem; every K is estimated from these


@dataclass(frozen=True)
class Mode:
    """What differs between E7 on the tiny model trained from scratch and on the real instruct model."""
    name: str
    recipe: str
    task: str  # the task module
    start: str  # what the model before RL is called in the report
    runs_sft: bool  # tiny: SFT from scratch first; real: the instruct model as it is (model.start_from=base)
    quick: tuple[str, ...]
    default_eval_rows: tuple[int, int]  # (full, --quick)
    behaviours: tuple[tuple[str, str], ...]  # (behaviour_counts key, label)


MODES = {
    "tiny": Mode("tiny", "tiny-math", "posttrain.tasks.math", "SFT", True,
                 ("sft.max_steps=120", "grpo.max_steps=6", "grpo.eval_every=3", "grpo.eval_rows=40",
                  "grpo.final_eval_rows=40", "grpo.save_every=0"), (200, 40),
                 (("frac_worked", "works the problem in columns"), ("frac_verification", "'check' (verification)"),
                  ("frac_self_correction", "self-correction words"))),
    "real": Mode("real", "smol-math", "posttrain.tasks.wordmath", "instruct", False,
                 ("grpo.max_steps=10", "grpo.eval_every=5", "grpo.eval_rows=48", "grpo.final_eval_rows=0",
                  "grpo.save_every=0"), (150, 48),
                 (("frac_verification", "verification phrases"), ("frac_self_correction", "self-correction phrases"),
                  ("frac_recomputation", "re-computation lines"))),
}
QUICK = list(MODES["tiny"].quick)


# ----------------------------------------------------------------------------- running stages
def posttrain(stage: str, recipe: str, output_dir: Path, threads: int, log: Path, overrides: list[str]) -> float:
    """Run `python -m posttrain STAGE --recipe RECIPE` as a user would; the wall time; raises with the log's tail."""
    took = run_stage([stage, "--recipe", recipe, f"run.output_dir={output_dir}", f"run.threads={threads}",
                      *overrides], log, threads, "reproduce_e7")
    print(f"[e7] posttrain {stage}: {took:.0f}s (log {log})", flush=True)
    return took


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(l) for l in path.read_text().splitlines() if l.strip()] if path.is_file() else []


def read_yaml(path: Path) -> dict:
    import yaml

    return yaml.safe_load(path.read_text()) if path.is_file() else {}


# ----------------------------------------------------------------------------- estimators
def pass_at_k(n: int, c: int, k: int) -> float:
    """Unbiased pass@k from n samples of which c are right (Chen et al. 2021, "Evaluating Large Language
    Models Trained on Code", eq. 1): 1 - C(n-c, k) / C(n, k)."""
    if n - c < k:
        return 1.0
    return 1.0 - math.comb(n - c, k) / math.comb(n, k)


def mixed_probability(n: int, c: int, k: int) -> float:
    """Probability that k of n samples (c right), drawn without replacement, are neither all right nor all wrong."""
    return 1.0 - (math.comb(n - c, k) + math.comb(c, k)) / math.comb(n, k)


def majority_correct(votes: list[tuple[str | None, bool]]) -> float:
    """Credit of a majority vote over (answer key, right?) pairs: 1 if the right answer has the most votes,
    1/t if it ties with t-1 others, else 0. Samples without an answer do not vote."""
    counts = collections.Counter(key for key, _ in votes if key is not None)
    if not counts:
        return 0.0
    right = {key for key, ok in votes if ok and key is not None}
    top = max(counts.values())
    leaders = [key for key, c in counts.items() if c == top]
    return sum(key in right for key in leaders) / len(leaders)


def k_metrics(per_problem: list[list[tuple[str | None, bool]]], n: int) -> dict:
    """pass@K (unbiased, from the n samples of each problem: (answer key, right?) pairs) for K = 1..n, and maj@K
    (disjoint groups of K) for K in KS up to n."""
    ks = [k for k in KS if k <= n]
    curve = [sum(pass_at_k(n, sum(ok for _, ok in p), k) for p in per_problem) / len(per_problem)
             for k in range(1, n + 1)]
    maj = {}
    for k in ks:
        groups = [p[i:i + k] for p in per_problem for i in range(0, n, k)]
        maj[k] = sum(majority_correct(g) for g in groups) / len(groups)
    return {"samples_per_problem": n, "sample_accuracy": curve[0], "pass_at_k": {k: curve[k - 1] for k in ks},
            "pass_curve": curve, "maj_at_k": maj}


def answer_key(verdict) -> str | None:
    """The verifier's normalised extracted answer (what majority voting compares), None when there is none."""
    d = verdict.details or {}
    if d.get("extracted") is None or verdict.reason in ("no answer found", "answer retracted"):
        return None
    return str(d.get("normalized") or d.get("extracted"))


# ----------------------------------------------------------------------------- evaluation of one model
def evaluate_model(model_dir: Path, rows: list[dict], max_new_tokens: int, pool, seed: int = 0, *,
                   mode: Mode = MODES["tiny"], temperature: float = 1.0) -> dict:
    """Greedy and N_SAMPLES-sample (at `temperature`) evaluation of one model on held-out rows; everything the
    report needs."""
    import torch

    from posttrain import chat
    from posttrain.models import load_model, load_tokenizer
    from posttrain.runtime import default_device
    from posttrain.rollout import SamplingParams, generate
    from posttrain.verifiers.registry import get_verifier

    task = importlib.import_module(mode.task)

    verifier = get_verifier("math")
    tok, model = load_tokenizer(model_dir), load_model(model_dir, device=default_device())
    chat.configure(tok, "auto", say=lambda _: None)  # prompts through the model's chat template, as the stages do
    prompts, refs = [r["prompt"] for r in rows], [r["answer"] for r in rows]
    keys = list(range(len(rows)))
    out: dict = {"model": str(model_dir), "rows": len(rows)}
    with torch.no_grad():
        t0 = time.time()
        greedy = generate(model, tok, prompts, SamplingParams(greedy=True, max_new_tokens=max_new_tokens),
                          prompt_keys=keys)
        t_greedy = time.time() - t0
        t0 = time.time()
        samples = generate(model, tok, prompts, SamplingParams(n=N_SAMPLES, temperature=temperature,
                                                               max_new_tokens=max_new_tokens, seed=seed),
                           prompt_keys=keys)
        t_samples = time.time() - t0
    g_verdicts = pool.score(verifier, [r.text for r in greedy], refs)
    s_verdicts = pool.score(verifier, [r.text for r in samples], [refs[r.prompt_index] for r in samples])
    g_right = [v.score >= 1.0 for v in g_verdicts]
    per_problem = [[] for _ in rows]  # (key, right) per sample, in sample order
    for r, v in zip(samples, s_verdicts):
        per_problem[r.prompt_index].append((answer_key(v), v.score >= 1.0))
    n = N_SAMPLES
    km = k_metrics(per_problem, n)
    pass_curve, maj = km["pass_curve"], km["maj_at_k"]
    g_len = [len(r.completion_ids) for r in greedy]
    s_len = [len(r.completion_ids) for r in samples]
    n_right = [sum(ok for _, ok in p) for p in per_problem]
    by_question = {}
    for name, want in (("direct-style question", True), ("other questions", False)):
        if mode.name != "tiny":
            break  # the two answer styles are tiny-math's
        idx = [i for i, r in enumerate(rows) if (r["meta"]["template"][1] == task.DIRECT_QUESTION) == want]
        if idx:
            by_question[name] = {"n": len(idx), "greedy_accuracy": sum(g_right[i] for i in idx) / len(idx),
                                 "greedy_worked": sum(task.is_worked(greedy[i].text) for i in idx) / len(idx),
                                 "worked_accuracy": (sum(g_right[i] for i in idx if task.is_worked(greedy[i].text))
                                                     / max(1, sum(task.is_worked(greedy[i].text) for i in idx)))}
    out.update({
        "greedy_by_question": by_question,
        "greedy_accuracy": sum(g_right) / len(rows),
        "sample_accuracy": pass_curve[0],
        "pass_at_k": {k: pass_curve[k - 1] for k in KS},
        "pass_curve": pass_curve,
        "maj_at_k": maj,
        "frac_mixed_groups_of_8": sum(mixed_probability(n, c, 8) for c in n_right) / len(rows),
        "frac_some_right_of_16": sum(c > 0 for c in n_right) / len(rows),
        "frac_all_right_of_16": sum(c == n for c in n_right) / len(rows),
        "greedy_tokens_per_problem": sum(g_len) / len(rows),
        "sample_tokens_per_sample": sum(s_len) / len(s_len),
        "greedy_seconds": t_greedy, "sample_seconds": t_samples,
        "greedy_truncated": sum(r.finish_reason == "length" for r in greedy) / len(rows),
        "behaviour_greedy": task.behaviour_counts([r.text for r in greedy]),
        "behaviour_samples": task.behaviour_counts([r.text for r in samples]),
        "greedy_reasons": dict(collections.Counter(v.reason for v in g_verdicts).most_common()),
        # tiny: the first held-out problems asking the direct-style question, where SFT and GRPO behave
        # differently; real: the first held-out problems
        "examples": [{"prompt": r["prompt"], "greedy": g.text, "right": ok}
                     for r, g, ok in zip(rows, greedy, g_right)
                     if mode.name != "tiny" or r["meta"]["template"][1] == task.DIRECT_QUESTION][:4],
        # samples showing a counted phrase (verification, self-correction, re-computation)
        "sample_examples": [{"prompt": rows[r.prompt_index]["prompt"], "sample": r.text, "right": v.score >= 1.0}
                            for r, v in zip(samples, s_verdicts) if _shows_behaviour(task, r.text, mode)][:3],
    })
    return out


def _shows_behaviour(task, text: str, mode: Mode) -> bool:
    counts = task.behaviour_counts([text])
    return any(counts[k] > 0 for k, _ in mode.behaviours if k != "frac_worked")


# ----------------------------------------------------------------------------- GRPO run
def grpo_curves(run_dir: Path) -> dict:
    """Held-out accuracy, lengths, tokens and time per step from the GRPO run's metrics.jsonl."""
    rows = read_jsonl(run_dir / "metrics.jsonl")
    cfg = read_yaml(run_dir / "config.yaml").get("grpo", {})
    P, K = cfg.get("prompts_per_step", 0), cfg.get("group_size", 0)
    train = [r for r in rows if "reward/mean" in r]
    evals = {}
    for r in rows:
        if "eval/accuracy" in r:
            evals[r["step"]] = r  # the last row of a step wins (the final eval repeats max_steps)
    tokens = 0.0
    cum_tokens, cum_time = [], []
    t = 0.0
    for r in train:
        rounds = r.get("resample/rounds", 1.0)
        tokens += P * K * rounds * r["completion/length"]
        t += r.get("time/step", 0.0)
        cum_tokens.append(tokens)
        cum_time.append(t)
    return {
        "prompts_per_step": P, "group_size": K, "steps": [r["step"] for r in train],
        "reward": [r["reward/mean"] for r in train],
        "train_length": [r["completion/length"] for r in train],
        "zero_var_frac": [r["zero_var_frac"] for r in train],
        "entropy": [r.get("entropy") for r in train],
        "cum_sampled_tokens": cum_tokens, "cum_step_seconds": cum_time,
        "eval_steps": sorted(evals), "eval_accuracy": [evals[s]["eval/accuracy"] for s in sorted(evals)],
        "eval_length": [evals[s].get("eval/length") for s in sorted(evals)],
        "sampled_tokens": tokens, "sampled_sequences": sum(P * K * r.get("resample/rounds", 1.0) for r in train),
        "trained_sequences": sum(r.get("rows/trained", 0.0) for r in train) * cfg.get("mu", 1),
        "config": cfg,
    }


def rollout_behaviour(run_dir: Path, mode: Mode = MODES["tiny"]) -> dict:
    """Phrase frequencies and lengths of the saved training rollouts, per saved step."""
    from posttrain.rollout import load_rollouts

    task = importlib.import_module(mode.task)
    out: dict[str, list] = {"steps": [], "length": [], **{k: [] for k, _ in mode.behaviours}}
    for path in sorted((run_dir / "rollouts").glob("step-*.jsonl")):
        rollouts = load_rollouts(path)
        b = task.behaviour_counts([r.text for r in rollouts])
        out["steps"].append(int(path.stem.split("-")[1]))
        for k, _ in mode.behaviours:
            out[k].append(b[k])
        out["length"].append(sum(len(r.completion_ids) for r in rollouts) / max(1, len(rollouts)))
    return out


def sft_cost(run_dir: Path, rows: list[dict], tokenizer_dir: Path) -> dict:
    """SFT's training tokens: steps x batch x the mean tokens of a training row (prompt + solution + eos)."""
    from posttrain.models import load_tokenizer

    if not (run_dir / "config.yaml").is_file():  # no SFT stage (the real instruct model)
        return {"steps": 0, "batch_size": 0, "tokens": 0.0, "sequences": 0, "mean_row_tokens": 0.0}
    cfg = read_yaml(run_dir / "config.yaml").get("sft", {})
    tok = load_tokenizer(tokenizer_dir)
    sample = rows[:500]
    mean_tokens = sum(len(tok(r["prompt"] + r["completion"])["input_ids"]) + 1 for r in sample) / max(1, len(sample))
    steps, batch = cfg.get("max_steps", 0), cfg.get("batch_size", 0)
    return {"steps": steps, "batch_size": batch, "tokens": steps * batch * mean_tokens,
            "sequences": steps * batch, "mean_row_tokens": mean_tokens}


# ----------------------------------------------------------------------------- analysis
def interpolate_k(curve: list[float], target: float) -> float | None:
    """Smallest (log-linearly interpolated) K at which a pass@K curve reaches `target`; None if never."""
    if curve[0] >= target:
        return 1.0
    for k in range(1, len(curve)):
        lo, hi = curve[k - 1], curve[k]
        if hi >= target:
            frac = (target - lo) / (hi - lo) if hi > lo else 1.0
            return math.exp(math.log(k) + frac * (math.log(k + 1) - math.log(k)))
    return None


def compute_table(res: dict) -> dict:
    """Compute spent per route, in generated tokens and seconds, and the break-even point."""
    sft, grpo = res["eval"]["sft"], res["eval"]["grpo"]
    g = res["grpo"]
    sec = res["seconds"]
    S = res.get("start_label", "SFT")
    rows = res["eval_rows"]
    per_sample_s = sft["sample_seconds"] / (rows * N_SAMPLES)
    routes = []
    for k in KS:
        routes.append({"route": f"{S}, maj@{k}" if k > 1 else f"{S}, 1 sample (T={res.get('temperature', 1.0):g})",
                       "accuracy": sft["maj_at_k"][k], "oracle_accuracy": sft["pass_at_k"][k],
                       "train_seconds": sec["sft"], "train_tokens": res["sft_cost"]["tokens"],
                       "inference_samples_per_problem": k,
                       "inference_tokens_per_problem": k * sft["sample_tokens_per_sample"],
                       "inference_seconds_per_problem": k * per_sample_s})
    routes.insert(0, {"route": f"{S}, greedy", "accuracy": sft["greedy_accuracy"], "oracle_accuracy": None,
                      "train_seconds": sec["sft"], "train_tokens": res["sft_cost"]["tokens"],
                      "inference_samples_per_problem": 1,
                      "inference_tokens_per_problem": sft["greedy_tokens_per_problem"],
                      "inference_seconds_per_problem": sft["greedy_seconds"] / rows})
    routes.append({"route": f"{S} + GRPO, greedy", "accuracy": grpo["greedy_accuracy"], "oracle_accuracy": None,
                   "train_seconds": sec["sft"] + sec["grpo"], "train_tokens": res["sft_cost"]["tokens"],
                   "grpo_sampled_tokens": g["sampled_tokens"], "grpo_sampled_sequences": g["sampled_sequences"],
                   "inference_samples_per_problem": 1,
                   "inference_tokens_per_problem": grpo["greedy_tokens_per_problem"],
                   "inference_seconds_per_problem": grpo["greedy_seconds"] / rows})
    for k in KS[1:]:
        routes.append({"route": f"{S} + GRPO, maj@{k}", "accuracy": grpo["maj_at_k"][k],
                       "oracle_accuracy": grpo["pass_at_k"][k], "train_seconds": sec["sft"] + sec["grpo"],
                       "train_tokens": res["sft_cost"]["tokens"], "grpo_sampled_tokens": g["sampled_tokens"],
                       "inference_samples_per_problem": k,
                       "inference_tokens_per_problem": k * grpo["sample_tokens_per_sample"],
                       "inference_seconds_per_problem": k * grpo["sample_seconds"] / (rows * N_SAMPLES)})
    # Matched inference compute: how many SFT samples does the oracle / majority vote need to reach GRPO greedy?
    k_oracle = interpolate_k(sft["pass_curve"], grpo["greedy_accuracy"])
    best_maj = max(KS, key=lambda k: sft["maj_at_k"][k])
    maj_tokens = best_maj * sft["sample_tokens_per_sample"] if best_maj > 1 else sft["greedy_tokens_per_problem"]
    maj_extra = maj_tokens - grpo["greedy_tokens_per_problem"]
    maj_extra_s = best_maj * per_sample_s - grpo["greedy_seconds"] / rows
    extra = None
    if k_oracle is not None:
        extra = k_oracle * sft["sample_tokens_per_sample"] - grpo["greedy_tokens_per_problem"]
    return {
        "routes": routes,
        "sft_oracle_k_matching_grpo_greedy": k_oracle,
        "sft_best_majority": {"k": best_maj, "accuracy": sft["maj_at_k"][best_maj],
                              "tokens_per_problem": maj_tokens,
                              "extra_tokens_per_problem_vs_grpo_greedy": maj_extra,
                              "break_even_problems_tokens": g["sampled_tokens"] / maj_extra if maj_extra > 0 else None,
                              "break_even_problems_seconds": sec["grpo"] / maj_extra_s if maj_extra_s > 0 else None},
        "grpo_training_tokens_sampled": g["sampled_tokens"],
        "grpo_training_seconds": sec["grpo"],
        "break_even_problems_tokens": (g["sampled_tokens"] / extra) if extra and extra > 0 else None,
        "extra_inference_tokens_per_problem_for_sft_oracle": extra,
    }


# ----------------------------------------------------------------------------- plots
def plots(res: dict, out: Path) -> dict[str, dict]:
    """The PNGs; returns {file: the data plotted} (written into e7.json)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sft, grpo, g = res["eval"]["sft"], res["eval"]["grpo"], res["grpo"]
    mode = MODES[res.get("mode", "tiny")]
    S, T = mode.start, res.get("temperature", 1.0)
    figs: dict[str, dict] = {}

    # 1. held-out greedy accuracy over GRPO steps, with the no-RL baselines
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ax.plot(g["eval_steps"], g["eval_accuracy"], "o-", color="tab:red", label="GRPO, greedy (held-out)")
    lines = {f"{S} greedy": (sft["greedy_accuracy"], "k", "-"),
             f"{S} maj@16": (sft["maj_at_k"][16], "tab:blue", "--"),
             f"{S} pass@4 (oracle)": (sft["pass_at_k"][4], "tab:green", ":"),
             f"{S} pass@16 (oracle)": (sft["pass_at_k"][16], "tab:green", "--")}
    for label, (y, c, ls) in lines.items():
        ax.axhline(y, color=c, ls=ls, lw=1, label=f"{label} {y:.2f}")
    ax.set_xlabel("GRPO step")
    ax.set_ylabel(f"held-out accuracy ({g.get('config', {}).get('eval_rows', '?')} problems during training)")
    ax.set_ylim(0, 1)
    ax.set_title("E7: held-out accuracy during GRPO vs sampling baselines without RL")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "e7_accuracy_curve.png", dpi=100)
    plt.close(fig)
    figs["e7_accuracy_curve.png"] = {"steps": g["eval_steps"], "grpo_greedy_accuracy": g["eval_accuracy"],
                                     "baselines": {k: v[0] for k, v in lines.items()}}

    # 2. accuracy against inference samples per problem
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ks = list(range(1, N_SAMPLES + 1))
    ax.plot(ks, sft["pass_curve"], "-", color="tab:green", label=f"{S} pass@K (oracle best-of-K)")
    ax.plot(ks, grpo["pass_curve"], "-", color="tab:orange", label="GRPO pass@K (oracle best-of-K)")
    ax.plot(KS, [sft["maj_at_k"][k] for k in KS], "s--", color="tab:blue", label=f"{S} maj@K")
    ax.plot(KS, [grpo["maj_at_k"][k] for k in KS], "s--", color="tab:red", label="GRPO maj@K")
    ax.plot([1], [sft["greedy_accuracy"]], "k^", ms=9, label=f"{S} greedy")
    ax.plot([1], [grpo["greedy_accuracy"]], "r*", ms=12, label="GRPO greedy")
    ax.set_xscale("log", base=2)
    ax.set_xticks([1, 2, 4, 8, 16])
    ax.set_xticklabels(["1", "2", "4", "8", "16"])
    ax.set_xlabel(f"samples per problem at inference (T={T:g})")
    ax.set_ylabel(f"held-out accuracy ({res['eval_rows']} problems)")
    ax.set_ylim(0, 1)
    ax.set_title("E7: inference-time compute vs RL")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "e7_inference_scaling.png", dpi=100)
    plt.close(fig)
    figs["e7_inference_scaling.png"] = {
        "k": ks, "sft_pass_at_k": sft["pass_curve"], "grpo_pass_at_k": grpo["pass_curve"],
        "maj_k": list(KS), "sft_maj_at_k": [sft["maj_at_k"][k] for k in KS],
        "grpo_maj_at_k": [grpo["maj_at_k"][k] for k in KS],
        "sft_greedy": sft["greedy_accuracy"], "grpo_greedy": grpo["greedy_accuracy"]}

    # 3. response length over training
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ax.plot(g["steps"], g["train_length"], "-", color="tab:purple", lw=1, label=f"training samples (T={T:g}), mean")
    ax.plot(g["eval_steps"], g["eval_length"], "o-", color="tab:red", label="held-out greedy, mean")
    ax.set_xlabel("GRPO step")
    ax.set_ylabel("completion length (tokens)")
    ax.set_title("E7: response length over GRPO training")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "e7_length.png", dpi=100)
    plt.close(fig)
    figs["e7_length.png"] = {"steps": g["steps"], "train_length": g["train_length"],
                             "eval_steps": g["eval_steps"], "eval_length": g["eval_length"]}

    # 4. verification / self-correction phrases
    b = res["behaviour_over_training"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    ax = axes[0]
    if b["steps"]:
        for (key, label), (marker, color) in zip(mode.behaviours, (("^-", "tab:red"), ("o-", "tab:blue"),
                                                                    ("s-", "tab:gray"))):
            ax.plot(b["steps"], b[key], marker, color=color, label=label)
    ax.set_xlabel("GRPO step")
    ax.set_ylabel("fraction of training samples")
    ax.set_title("phrases in GRPO's training samples")
    ax.legend(fontsize=8)
    ax = axes[1]
    short = {"frac_worked": "worked", "frac_verification": "check" if mode.name == "tiny" else "verify",
             "frac_self_correction": "self-corr.", "frac_recomputation": "re-comp."}
    keys = [(who, k) for k, _ in mode.behaviours for who in ("greedy", "samples")]
    labels = [f"{who}\n{short[k]}" for who, k in keys]
    before = [sft[f"behaviour_{who}"][k] for who, k in keys]
    after = [grpo[f"behaviour_{who}"][k] for who, k in keys]
    x = range(len(labels))
    ax.bar([i - 0.2 for i in x], before, 0.4, label=S, color="tab:gray")
    ax.bar([i + 0.2 for i in x], after, 0.4, label=f"{S} + GRPO", color="tab:red")
    ax.set_xticks(list(x))
    ax.set_xticklabels(labels, fontsize=8)
    ax.set_ylabel("fraction of held-out completions")
    ax.set_title("before / after RL (held-out)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "e7_behaviour.png", dpi=100)
    plt.close(fig)
    figs["e7_behaviour.png"] = {"over_training": b, "labels": [l.replace("\n", " ") for l in labels],
                                "sft": before, "grpo": after}

    # 5. accuracy against total generated tokens for a workload of problems
    c = res["compute"]
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for r in c["routes"]:
        ax.scatter(r["inference_tokens_per_problem"], r["accuracy"], s=40,
                   color="tab:red" if "GRPO" in r["route"] else "tab:blue")
        ax.annotate(r["route"], (r["inference_tokens_per_problem"], r["accuracy"]), fontsize=7,
                    xytext=(4, 3), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlim(right=3 * max(r["inference_tokens_per_problem"] for r in c["routes"]))
    ax.set_xlabel("tokens generated per problem at inference (log)")
    ax.set_ylabel("held-out accuracy (no oracle)")
    ax.set_ylim(0, 1)
    ax.set_title(f"E7: accuracy vs inference tokens (GRPO training sampled {c['grpo_training_tokens_sampled']:,.0f} tokens)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "e7_compute.png", dpi=100)
    plt.close(fig)
    figs["e7_compute.png"] = {"routes": c["routes"]}
    return figs


# ----------------------------------------------------------------------------- report
def pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}%"


def report_md(res: dict) -> str:
    sft, grpo, g, c = res["eval"]["sft"], res["eval"]["grpo"], res["grpo"], res["compute"]
    sec = res["seconds"]
    gain = grpo["greedy_accuracy"] - sft["greedy_accuracy"]
    mode = MODES[res.get("mode", "tiny")]
    S, T, tiny = mode.start, res.get("temperature", 1.0), mode.name == "tiny"
    L = []
    L.append(f"# E7: GRPO vs best-of-K on {mode.recipe}{' (quick smoke run)' if res['quick'] else ''}\n")
    load = res.get("load_average")  # (start, end): 1-minute load averages; a shared machine slows every figure
    busy = f"load average {load[0]:.1f} at the start, {load[1]:.1f} at the end" if load else "load not recorded"
    L.append(f"Runtime: {res['runtime_s'] / 60:.1f} min in all on this machine ({res.get('cpu', 'CPU not recorded')}, "
             f"{os.cpu_count()} cores, {busy}; torch threads per stage: {res['threads'] or 'default'}): "
             + (f"SFT {sec['sft']:.0f} s, " if mode.runs_sft else "") + f"GRPO {sec['grpo']:.0f} s, "
             f"baseline and final evaluations {sec['eval']:.0f} s" + (" (reused runs: " + ", ".join(res["reused"]) + ")"
                                                                   if res["reused"] else "") + ".\n")
    model_text = (f"Model: `{res['preset']}` preset, {res['parameters'] / 1e6:.2f}M parameters, trained from scratch. "
                  f"Held-out: {res['eval_rows']} problems (number tuples and template pairings never seen in training)"
                  if tiny else
                  f"Model: `{res['preset']}` ({res['parameters'] / 1e6:.1f}M parameters), the instruct model as it is: "
                  f"no SFT, prompts through its own chat template. Held-out: {res['eval_rows']} word problems of "
                  f"difficulty {res.get('difficulty')} (number tuples never seen in training, larger operands, held-out "
                  "phrasings, names and items)")
    L.append(f"Command: `python scripts/reproduce_e7.py{'' if tiny else ' --model real'}{' --quick' if res['quick'] else ''}"
             f"{''.join(' --set ' + s for s in res['overrides'])}`. {model_text}. Samples: {N_SAMPLES} per problem at "
             f"T={T:g} (the temperature GRPO samples at); every K is estimated from them. Generation here and in "
             f"the stages: rollout.dtype={res.get('rollout_dtype', 'float32')}; training: run.mixed_precision="
             f"{res.get('mixed_precision', 'no')}.\n")
    L.append("## Result\n")
    L.append(f"- {S} greedy accuracy **{pct(sft['greedy_accuracy'])}**; after GRPO **{pct(grpo['greedy_accuracy'])}** "
             f"({'+' if gain >= 0 else ''}{100 * gain:.1f} points) after {len(g['steps'])} GRPO steps "
             f"({sec['grpo'] / 60:.1f} min).")
    if not tiny:
        L.append(f"- Target (issue: GRPO raises held-out greedy accuracy by at least 10 points over the instruct model): "
                 f"**{'met' if gain >= 0.10 else 'not met'}** ({'+' if gain >= 0 else ''}{100 * gain:.1f} points on "
                 f"{res['eval_rows']} problems; one problem is {100 / res['eval_rows']:.1f} points).")
    if gain <= 0:
        L.append(f"- GRPO did not improve greedy accuracy here, so no sampling budget of the {S} model is needed to "
                 "match it.")
    elif c["sft_oracle_k_matching_grpo_greedy"] is not None:
        L.append(f"- The {S} model needs about **K = {c['sft_oracle_k_matching_grpo_greedy']:.1f}** samples with a "
                 f"verifier oracle picking a right one to match one greedy answer of the GRPO model.")
    else:
        L.append(f"- Even an oracle best-of-{N_SAMPLES} of the {S} model ({pct(sft['pass_at_k'][16])}) stays below "
                 f"one greedy answer of the GRPO model.")
    L.append(f"- Without an oracle, the {S} model's best majority vote is maj@{c['sft_best_majority']['k']} = "
             f"{pct(c['sft_best_majority']['accuracy'])}, at {c['sft_best_majority']['k']} samples per problem.")
    bm = c["sft_best_majority"]
    if bm["break_even_problems_tokens"] and grpo["greedy_accuracy"] >= bm["accuracy"]:
        L.append(f"- Compute against that realistic baseline: GRPO training sampled {g['sampled_tokens']:,.0f} tokens "
                 f"in {sec['grpo']:.0f} s; {S} maj@{bm['k']} generates {bm['extra_tokens_per_problem_vs_grpo_greedy']:.0f} "
                 f"more tokens per problem than one greedy GRPO answer, so GRPO's training pays for itself after about "
                 f"{bm['break_even_problems_tokens']:,.0f} problems in generated tokens "
                 + (f"({bm['break_even_problems_seconds']:,.0f} problems in measured seconds)"
                    if bm["break_even_problems_seconds"] else "")
                 + f", and is {100 * (grpo['greedy_accuracy'] - bm['accuracy']):.1f} points more accurate.")
    if c["break_even_problems_tokens"]:
        L.append(f"- Compute: GRPO training sampled {g['sampled_tokens']:,.0f} tokens "
                 f"({g['sampled_sequences']:,.0f} completions); matching it by oracle best-of-K costs "
                 f"{c['extra_inference_tokens_per_problem_for_sft_oracle']:.0f} extra tokens per problem, so RL is "
                 f"cheaper in generated tokens after about {c['break_even_problems_tokens']:,.0f} problems.")
    L.append("")
    L.append("## Accuracy at matched inference compute (held-out)\n")
    L.append(f"| samples / problem | {S} | {S} + GRPO | {S} oracle pass@K | GRPO oracle pass@K |")
    L.append("|---|---|---|---|---|")
    L.append(f"| 1 (greedy) | {pct(sft['greedy_accuracy'])} | {pct(grpo['greedy_accuracy'])} | | |")
    for k in KS:
        label = f"{k} (T={T:g}, " + ("one sample)" if k == 1 else "majority vote)")
        L.append(f"| {label} | {pct(sft['maj_at_k'][k])} | {pct(grpo['maj_at_k'][k])} | {pct(sft['pass_at_k'][k])} | "
                 f"{pct(grpo['pass_at_k'][k])} |")
    L.append("")
    L.append("pass@K needs the reference answer at inference time (a verifier oracle); majority vote does not. "
             f"Fraction of problems with some right answer among {N_SAMPLES} samples: {S} "
             f"{pct(sft['frac_some_right_of_16'])}, GRPO {pct(grpo['frac_some_right_of_16'])}; all {N_SAMPLES} right: "
             f"{S} {pct(sft['frac_all_right_of_16'])}, GRPO {pct(grpo['frac_all_right_of_16'])}. Problems whose groups of 8 "
             f"are mixed (GRPO's learning signal): {S} {pct(sft['frac_mixed_groups_of_8'])}, GRPO "
             f"{pct(grpo['frac_mixed_groups_of_8'])}.\n")
    L.append("![accuracy curve](e7_accuracy_curve.png)\n")
    L.append("![inference scaling](e7_inference_scaling.png)\n")
    L.append("## Compute\n")
    L.append("| route | accuracy | training (s) | training tokens | inference samples / problem | inference tokens / problem | inference s / problem |")
    L.append("|---|---|---|---|---|---|---|")
    for r in c["routes"]:
        tt = (f"{r['train_tokens']:,.0f} SFT" if mode.runs_sft else "none") + (f" + {r['grpo_sampled_tokens']:,.0f} GRPO-sampled"
                                                  if r.get("grpo_sampled_tokens") else "")
        L.append(f"| {r['route']} | {pct(r['accuracy'])} | {r['train_seconds']:.0f} | {tt} | "
                 f"{r['inference_samples_per_problem']} | {r['inference_tokens_per_problem']:.0f} | "
                 f"{r['inference_seconds_per_problem'] * 1000:.1f} ms |")
    L.append("")
    L.append((f"SFT processed {res['sft_cost']['sequences']:,} training sequences ({res['sft_cost']['steps']} steps x "
              f"batch {res['sft_cost']['batch_size']}, {res['sft_cost']['mean_row_tokens']:.0f} tokens each). "
              if mode.runs_sft else "The instruct model had no training here (its own pre- and post-training is not "
              "counted). ") + f"GRPO sampled "
             f"{g['sampled_sequences']:,.0f} completions ({g['prompts_per_step']} prompts x {g['group_size']} per step, plus "
             "the resampling rounds of dynamic sampling) "
             f"and trained on {g['trained_sequences']:,.0f} sequences (zero-variance groups are skipped). Inference "
             "seconds are measured in this script's batched generation (all problems at once), single process.\n")
    L.append("![compute](e7_compute.png)\n")
    L.append("## Behaviour: response length and verification / self-correction phrases\n")
    first_len = g["train_length"][0] if g["train_length"] else float("nan")
    last_len = sum(g["train_length"][-5:]) / max(1, len(g["train_length"][-5:])) if g["train_length"] else float("nan")
    L.append(f"- Training samples: {first_len:.1f} tokens at the first step, {last_len:.1f} over the last 5 steps. "
             f"Held-out greedy: {S} {sft['greedy_tokens_per_problem']:.1f} tokens, GRPO "
             f"{grpo['greedy_tokens_per_problem']:.1f}; truncated at the budget: {S} {pct(sft['greedy_truncated'])}, "
             f"GRPO {pct(grpo['greedy_truncated'])}.")
    labels = dict(mode.behaviours)
    for who, m in ((S, sft), (f"{S} + GRPO", grpo)):
        bg, bs = m["behaviour_greedy"], m["behaviour_samples"]
        L.append(f"- {who}: " + "; ".join(f"{label} in {pct(bg[k])} of greedy answers and {pct(bs[k])} of samples"
                                          for k, label in mode.behaviours) + ".")
    b = res["behaviour_over_training"]
    if b["steps"]:
        L.append(f"- In GRPO's saved training rollouts (steps {b['steps'][0]}..{b['steps'][-1]}): "
                 + "; ".join(f"{label} {pct(b[k][0])} -> {pct(b[k][-1])} of samples" for k, label in labels.items()) + ".")
    L.append("")
    if tiny:
        L.append("What these phrases are: the SFT data has an optional line `Check: 66+19=85` (the inverse of the last "
                 "operation, numbers copied from the line above) in 25% of training solutions and never in held-out "
                 "solutions; it cannot change the answer, so a change in its frequency under RL is drift or a side effect "
                 "of length, not learned verification. No self-correction word is in the SFT data: a tiny model trained "
                 "from scratch has no such words to discover, unlike the pretrained models in which R1-style 'aha' "
                 "behaviour was reported.\n")
    else:
        L.append("What is counted (`posttrain.tasks.wordmath.behaviour_counts`, case-insensitive whole words): "
                 "verification = " + ", ".join(f"'{p}'" for p in res.get("phrases", {}).get("verification", []))
                 + "; self-correction = " + ", ".join(f"'{p}'" for p in res.get("phrases", {}).get("self_correction", []))
                 + "; a re-computation line is an equation (`a + b = c`) whose left side already appeared earlier in the "
                 "same answer.\n")
        for who, m in ((S, sft), (f"{S} + GRPO", grpo)):
            for ex in m.get("sample_examples", [])[:2]:
                L.append(f"{who}, a sample showing a counted behaviour ({'right' if ex['right'] else 'wrong'}):\n\n"
                         f"```\n{ex['prompt']}\n{ex['sample'][:600]}\n```\n")
    L.append("![length](e7_length.png)\n")
    L.append("![behaviour](e7_behaviour.png)\n")
    if tiny:
        _where_the_gain_comes_from(L, res, sft, grpo)
    L.append("## Why held-out greedy answers fail\n")
    for who, m in ((S, sft), (f"{S} + GRPO", grpo)):
        L.append(f"- {who}: " + ", ".join(f"{k} {v}" for k, v in m["greedy_reasons"].items()))
    L.append("")
    L.append(f"## Examples (held-out, greedy{', a direct-style question' if tiny else ''})\n")
    for who, m in ((S, sft), (f"{S} + GRPO", grpo)):
        if not m["examples"]:
            continue
        ex = m["examples"][0]
        L.append(f"{who} ({'right' if ex['right'] else 'wrong'}):\n\n```\n{ex['prompt']}{'' if tiny else chr(10)}"
                 f"{ex['greedy']}\n```\n")
    L.append("## Settings\n")
    L.append(f"GRPO config (resolved): `{json.dumps({k: v for k, v in g['config'].items() if k in ('prompts_per_step', 'group_size', 'max_steps', 'lr', 'beta', 'estimator', 'std_scale', 'aggregation', 'zero_variance', 'mu', 'max_new_tokens', 'temperature', 'clip_eps', 'clip_eps_high')})}`. "
             f"Run directories: `{res['runs_dir']}`. Every number above and every plotted series is in `e7.json`.\n")
    if res.get("stage_plots"):
        L.append("Each stage's own metric plots (loss, reward, KL, lengths, ...: `posttrain plot`, the same function): "
                 + ", ".join(f"[{name}]({folder})" for name, folder in res["stage_plots"].items()) + ".\n")
    return "\n".join(L)


def _where_the_gain_comes_from(L: list[str], res: dict, sft: dict, grpo: dict) -> None:
    """tiny-math only: accuracy by answer style (the recipe's two styles are where its room for RL is)."""
    L.append("## Where the gain comes from\n")
    L.append(f"SFT data answers the question \"How many ... are there now?\" without working in "
             f"{res['direct_prob']:.0%} of its training rows (all other phrasings are worked). Held-out greedy answers:\n")
    L.append("| problems | n | SFT accuracy | SFT worked in columns | GRPO accuracy | GRPO worked in columns |")
    L.append("|---|---|---|---|---|---|")
    for name, a in sft["greedy_by_question"].items():
        b2 = grpo["greedy_by_question"][name]
        L.append(f"| {name} | {a['n']} | {pct(a['greedy_accuracy'])} | {pct(a['greedy_worked'])} | "
                 f"{pct(b2['greedy_accuracy'])} | {pct(b2['greedy_worked'])} |")
    L.append("")
    L.append("Accuracy of the greedy answers that are worked in columns (the arithmetic itself): SFT "
             + ", ".join(f"{k} {pct(v['worked_accuracy'])}" for k, v in sft["greedy_by_question"].items())
             + "; GRPO " + ", ".join(f"{k} {pct(v['worked_accuracy'])}" for k, v in grpo["greedy_by_question"].items())
             + ".\n")


# ----------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", choices=sorted(MODES), default="tiny",
                    help="tiny: tiny-math on a model trained from scratch (SFT first); real: smol-math on "
                         "SmolLM2-135M-Instruct as it is (fetch it first: posttrain models fetch --help)")
    ap.add_argument("--quick", action="store_true", help="a smoke run: short SFT and GRPO, fewer held-out problems")
    ap.add_argument("--out", type=Path, default=None,
                    help="output directory (default runs/e7[-real][-quick])")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per stage and here (0: torch's default)")
    ap.add_argument("--eval-rows", type=int, default=None,
                    help="held-out problems for the baselines (default: tiny 200, quick 40; real 150, quick 48)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.KEY=VALUE",
                    help="config override passed to both stages, e.g. grpo.max_steps=100 (repeatable)")
    ap.add_argument("--fresh", action="store_true", help="redo the SFT and GRPO runs even when they exist in --out")
    args = ap.parse_args(argv)
    mode = MODES[args.model]
    out = prepare(args, "reproduce_e7", ROOT / "runs" / ("e7" + ("-real" if mode.name == "real" else "")
                                                       + ("-quick" if args.quick else "")))

    from posttrain.cli import STAGES
    from posttrain.config import resolve
    from posttrain.models import count_parameters, load_model
    from posttrain.models import is_model_dir
    from posttrain.tasks import load_split
    from posttrain.runtime import cpu_model
    from posttrain.verifiers.runner import VerifierPool

    task_module = importlib.import_module(mode.task)
    t_all, load_start = time.time(), os.getloadavg()[0]
    overrides = (list(mode.quick) if args.quick else []) + args.overrides
    runs = out / "runs"
    run_root = runs / mode.recipe
    timing_file = out / "seconds.json"
    seconds = json.loads(timing_file.read_text()) if timing_file.is_file() else {}
    reused = []
    res_eval = resolve(mode.recipe, "grpo", STAGES["grpo"].load()[0], [f"run.output_dir={runs}", *overrides])

    # 1. SFT (tiny), or the instruct model as it is (real)
    if not mode.runs_sft:
        start_dir = Path(res_eval.model.path)
        if not is_model_dir(start_dir):
            raise SystemExit(f"reproduce_e7: model.path {str(start_dir)!r} is not a model directory; fetch the model "
                             f"first: posttrain models fetch smollm2-135m-instruct {start_dir}")
        if seconds.get("start") != str(start_dir.resolve()):  # another model: nothing of the old runs applies
            seconds = {"start": str(start_dir.resolve())}
            shutil.rmtree(run_root / "grpo", ignore_errors=True)
        seconds["sft"] = 0.0
        timing_file.write_text(json.dumps(seconds))
    elif (run_root / "sft" / "final").is_dir() and "sft" in seconds:
        start_dir = run_root / "sft" / "final"
        print(f"[e7] reusing the SFT model in {run_root / 'sft'}")
        reused.append("sft")
    else:
        start_dir = run_root / "sft" / "final"
        seconds["sft"] = posttrain("sft", mode.recipe, runs, args.threads, out / "logs" / "sft.log", overrides)
        seconds.pop("grpo", None)  # a new SFT model invalidates any GRPO run on the old one
        shutil.rmtree(run_root / "grpo", ignore_errors=True)
        timing_file.write_text(json.dumps(seconds))

    from dataclasses import asdict

    from posttrain.rollout import configure

    configure(**asdict(res_eval.rollout))  # this script's generation runs as the recipe's stages do (rollout.dtype)
    n_rows = args.eval_rows or mode.default_eval_rows[args.quick]
    rows = load_split(res_eval.task, "eval")
    if len(rows) < n_rows:
        res_eval.task.n_eval = n_rows
        rows = load_split(res_eval.task, "eval")
    rows = rows[:n_rows]
    max_new = res_eval.stage_cfg.max_new_tokens
    temperature = res_eval.stage_cfg.temperature
    pool = VerifierPool(workers=1)
    t_eval = 0.0
    try:
        # 2. baselines without RL
        t0 = time.time()
        sft_eval = evaluate_model(start_dir, rows, max_new, pool, mode=mode, temperature=temperature)
        t_eval += time.time() - t0
        print(f"[e7] {mode.start}: greedy {sft_eval['greedy_accuracy']:.3f}, pass@K {sft_eval['pass_at_k']}, "
              f"maj@K {sft_eval['maj_at_k']} ({time.time() - t0:.0f}s)", flush=True)

        # 3. GRPO
        grpo_dir = run_root / "grpo"
        if (grpo_dir / "final").is_dir() and "grpo" in seconds:
            print(f"[e7] reusing the GRPO run in {grpo_dir}")
            reused.append("grpo")
        else:
            max_steps = res_eval.stage_cfg.max_steps
            every = max(1, max_steps // 10)
            seconds["grpo"] = posttrain("grpo", mode.recipe, runs, args.threads, out / "logs" / "grpo.log",
                                        overrides + [f"grpo.save_rollouts_every={every}"])
            timing_file.write_text(json.dumps(seconds))

        # 4. the GRPO model, behaviour, compute
        t0 = time.time()
        grpo_eval = evaluate_model(grpo_dir / "final", rows, max_new, pool, mode=mode, temperature=temperature)
        t_eval += time.time() - t0
        print(f"[e7] GRPO: greedy {grpo_eval['greedy_accuracy']:.3f}, pass@K {grpo_eval['pass_at_k']}, "
              f"maj@K {grpo_eval['maj_at_k']} ({time.time() - t0:.0f}s)", flush=True)
    finally:
        pool.close()

    res = {
        "mode": mode.name, "start_label": mode.start, "temperature": temperature,
        "rollout_dtype": res_eval.rollout.dtype, "mixed_precision": res_eval.run.mixed_precision,
        "quick": args.quick, "overrides": args.overrides, "threads": args.threads, "eval_rows": len(rows),
        "preset": res_eval.model.path, "parameters": count_parameters(load_model(start_dir)),
        "difficulty": res_eval.task.difficulty or getattr(task_module, "DEFAULT_DIFFICULTY", None),
        "phrases": {"verification": list(task_module.VERIFICATION_PHRASES),
                    "self_correction": list(task_module.SELF_CORRECTION_PHRASES)},
        "runs_dir": str(runs), "reused": reused, "direct_prob": getattr(task_module, "DIRECT_PROB", None),
        "seconds": {"sft": seconds["sft"], "grpo": seconds["grpo"], "eval": t_eval},
        "eval": {"sft": sft_eval, "grpo": grpo_eval},
        "grpo": grpo_curves(grpo_dir),
        "behaviour_over_training": rollout_behaviour(grpo_dir, mode),
        "sft_cost": sft_cost(run_root / "sft", load_split(res_eval.task, "train"), start_dir),
        "grpo_eval_json": json.loads((grpo_dir / "eval.json").read_text()) if (grpo_dir / "eval.json").is_file() else {},
    }
    res["compute"] = compute_table(res)
    res["figures"] = plots(res, out)
    from posttrain.plots import plot_runs  # `posttrain plot` of each stage, linked from the report

    res["stage_plots"] = plot_runs({"sft": run_root / "sft", "grpo": grpo_dir}, out, say=lambda m: print(f"[e7] {m}"))
    res["runtime_s"] = time.time() - t_all + sum(seconds[k] for k in ("sft", "grpo") if k in reused)
    res["load_average"], res["cpu"] = (load_start, os.getloadavg()[0]), cpu_model()
    (out / "e7.json").write_text(json.dumps(res, indent=2, default=str))
    (out / "report.md").write_text(report_md(res))
    print(f"[e7] {mode.start} greedy {sft_eval['greedy_accuracy']:.3f} -> GRPO greedy {grpo_eval['greedy_accuracy']:.3f}; "
          f"report {out / 'report.md'} ({res['runtime_s'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
