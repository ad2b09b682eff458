"""Tool-use RL on a real instruct model (issue 35): what SFT and GRPO with a calculator change on SmolLM2-135M-Instruct.

Pipeline, through the public CLI and API only (each stage a `python -m posttrain` subprocess, as a user runs it):
  1. `posttrain sft --recipe smol-tools`: a LoRA SFT of the instruct model on seeded tool-use demonstrations
     (word problems solved with one calculator call; one in eight recovers from a refused call first). Timed.
  2. `posttrain grpo --recipe smol-tools` from it: multi-turn GRPO in the `calc-words` environment (the model may
     call the calculator, reads the results, answers in prose; the math verifier scores the answer). Timed, with
     the training episodes saved every few steps.
  3. `posttrain grpo --recipe smol-math task.difficulty=4`: the E7 arm, GRPO without tools from the instruct
     model, on the same problems (word-math level 4), at the same GRPO budget (steps, prompts per step, episodes
     per prompt; its own recipe's learning rate). Timed.
  4. Evaluation here, on the same N held-out problems, greedy and 16 samples per problem (at the recipe's GRPO
     temperature) of: the instruct model without tools (plain answers, the math verifier), the instruct model with
     the tool (prompted only: the tools listed in the system message), after SFT, after GRPO with tools, after GRPO
     without tools. From the samples: pass@K (verifier-oracle best-of-K, Chen et al. 2021's unbiased estimator)
     and maj@K (majority vote over the verifier's extracted answers) at K in {1, 4, 16}. The prompted instruct
     model is evaluated greedy only (its episodes run to the turn limits: 16 samples of each would cost more than
     the rest of the evaluation). The SFT and GRPO models are also scored greedy on a second held-out set, word
     problems in phrasings of our own (`--own`, default data/word-calc-own.jsonl: written apart from the
     generator's templates, never trained or tuned on): does the accuracy hold on problems the generator did not write?
  5. Behaviour of every tool model's episodes and of the saved training episodes over GRPO steps: tool-call rate,
     valid-call rate, calls per problem, recovery after a tool error, answers that ignore the last tool result, and
     why each wrong greedy answer is wrong (no call, no valid call, a wrong expression computed exactly, the right
     result ignored, no answer turn), with examples. Compute: tokens sampled, environment tokens, tool seconds,
     seconds.
  6. Report under --out: report.md, PNG plots, tools.json (the data of every figure and table), and two verdicts:
     issue 35's (GRPO with tools against the instruct model and against GRPO without tools) and issue 49's (RL
     against its SFT start: greedy, pass@16, the phrasings of our own; `RL_GAIN`, `PASS_DROP`, `OWN_GAIN`).

CPU:  posttrain models fetch smollm2-135m-instruct models/smollm2-135m-instruct     once (~40 s, PyPI)
      python scripts/reproduce_tools.py            the shipped recipes; measured runtime in RESULTS.md (smol-tools report)
      python scripts/reproduce_tools.py --quick    a smoke run of the same pipeline: short SFT and GRPO, 32 held-out
                                                   problems, 4 samples each
Options: --out DIR (default runs/tools[-quick]), --threads N (torch threads per stage and here; 0 = torch's default),
         --eval-rows N, --fresh (redo everything; by default finished stages in --out are reused), --set
         stage.key=value overrides for the smol-tools stages (e.g. --set grpo.lr=5e-5; the no-tool arm takes the
         GRPO budget keys max_steps, prompts_per_step and group_size from them), --own FILE ('' skips it).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from reproduce_e7 import (KS, MODES, answer_key, evaluate_model, k_metrics, pct, read_jsonl,  # noqa: E402
                          read_yaml)
from stage_runner import prepare, run_stage  # noqa: E402  (scripts/, this file's folder)

TOOLS, NO_TOOLS = "smol-tools", "smol-math"
OWN = ROOT / "data" / "word-calc-own.jsonl"  # held-out word problems in phrasings of our own (data/README.md)
DIFFICULTY = 4  # word-math level 4, the smol-tools problems (the no-tool arm is set to it)
BUDGET_KEYS = ("max_steps", "prompts_per_step", "group_size")  # the GRPO budget both arms share
# --quick: 30 SFT steps teach the call (held-out greedy 0.43, every episode a valid call: RESULTS.md, "GRPO moves
# smol-tools past its SFT start"); 12 taught none.
QUICK = ("sft.max_steps=30", "sft.final_eval_rows=8", "grpo.max_steps=2", "grpo.eval_every=1", "grpo.eval_rows=8",
         "grpo.prompts_per_step=4")
LABELS = {"instruct": "instruct, no tool", "instruct_tools": "instruct, tool prompted", "sft": "SFT with the tool",
          "grpo": "SFT + GRPO with the tool", "grpo_no_tools": "GRPO without tools (E7 arm)"}
CAUSES = ("right", "no call", "no valid call", "no answer turn", "wrong expression", "right result ignored")


def say(msg: str) -> None:
    print(f"[tools] {msg}", flush=True)


# ----------------------------------------------------------------------------- episodes: behaviour
def _valid_calls(ep: dict) -> list[dict]:
    return [c for t in ep["turns"] for c in t["tool_calls"] if c["error"] is None]


def _same_number(check, text: str, number: str) -> bool:
    """Whether the math verifier reads `text`'s answer as `number` (a tool result or the reference)."""
    return check(text, str(number)).score >= 1.0


def cause(ep: dict, reference: str, reward: float, check) -> str:
    """Why an episode scored what it did (CAUSES): right; no call; calls but none valid; no answer turn (a limit
    hit); a wrong expression (no valid call returned the reference); the right result ignored (a call returned the
    reference, the answer says otherwise)."""
    if reward >= 1.0:
        return "right"
    calls = [c for t in ep["turns"] for c in t["tool_calls"]]
    if not calls:
        return "no call"
    valid = _valid_calls(ep)
    if not valid:
        return "no valid call"
    if ep["finish"] != "answer":
        return "no answer turn"
    if any(_same_number(check, c["content"], reference) for c in valid):
        return "right result ignored"
    return "wrong expression"


def ignores_result(ep: dict, check) -> bool | None:
    """An answer turn after a valid call whose answer is not the last valid call's result (None: not applicable)."""
    valid = _valid_calls(ep)
    if ep["finish"] != "answer" or not valid or not ep["turns"]:
        return None
    return not _same_number(check, ep["turns"][-1]["text"], valid[-1]["content"])


def behaviour(episodes: list[dict], check) -> dict[str, float]:
    """Rates over episodes: called a tool, valid calls / calls, calls per episode, turns, recovery after a tool
    error (an errored call followed by a valid one), answers ignoring the last result, tokens and tool seconds."""
    n = max(1, len(episodes))
    calls = [c for e in episodes for t in e["turns"] for c in t["tool_calls"]]
    errored = [e for e in episodes if any(c["error"] for t in e["turns"] for c in t["tool_calls"])]

    def recovered(e: dict) -> bool:
        seq = [c for t in e["turns"] for c in t["tool_calls"]]
        first_bad = next(i for i, c in enumerate(seq) if c["error"])
        return any(c["error"] is None for c in seq[first_bad + 1:])

    ign = [x for x in (ignores_result(e, check) for e in episodes) if x is not None]
    return {
        "called_a_tool": sum(any(t["tool_calls"] for t in e["turns"]) for e in episodes) / n,
        "valid_call_rate": sum(c["error"] is None for c in calls) / max(1, len(calls)),
        "calls_per_episode": len(calls) / n,
        "turns_per_episode": sum(len(e["turns"]) for e in episodes) / n,
        "answered": sum(e["finish"] == "answer" for e in episodes) / n,
        "episodes_with_a_tool_error": len(errored) / n,
        "recovered_after_error": (sum(recovered(e) for e in errored) / len(errored)) if errored else None,
        "ignores_last_result": (sum(ign) / len(ign)) if ign else None,
        "sampled_tokens": sum(t["sampled_tokens"] for e in episodes for t in e["turns"]) / n,
        "env_tokens": sum(t["env_tokens"] for e in episodes for t in e["turns"]) / n,
        "tool_seconds": sum(c["seconds"] for c in calls) / n,
    }


def transcript(ep: dict) -> str:
    """An episode's assistant turns and tool results, one line each (for the report's examples)."""
    lines = []
    for t in ep["turns"]:
        lines.append("assistant: " + t["text"].strip().replace("\n", " "))
        for c in t["tool_calls"]:
            lines.append("tool: " + str(c["content"]).strip().replace("\n", " ")[:160])
    return "\n".join(lines)


# ----------------------------------------------------------------------------- evaluation of one tool model
def evaluate_episodes(model_dir: Path, problems: list[dict], env, samples: int, temperature: float,
                      seed: int = 0) -> dict:
    """Greedy episodes (and `samples` sampled ones per problem, 0: none) of `env` on `problems`: accuracy, pass@K,
    maj@K, behaviour, causes of wrong greedy answers, compute, examples."""
    import torch

    from posttrain import chat
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout.multiturn import generate_episodes
    from posttrain.runtime import default_device
    from posttrain.verifiers.envs import ToolRunner
    from posttrain.verifiers.math_answer import MathVerifier

    check = MathVerifier().check
    tok, model = load_tokenizer(model_dir), load_model(model_dir, device=default_device())
    chat.configure(tok, "auto", say=lambda _: None)
    keys = list(range(len(problems)))
    runner = ToolRunner()
    out: dict = {"model": str(model_dir), "rows": len(problems)}
    try:
        with torch.no_grad():
            t0 = time.time()
            greedy = generate_episodes(model, tok, env, problems, greedy=True, prompt_keys=keys, runner=runner)
            out["greedy_seconds"] = time.time() - t0
            sampled = []
            if samples:
                t0 = time.time()
                sampled = generate_episodes(model, tok, env, problems, n=samples, temperature=temperature, seed=seed,
                                            prompt_keys=keys, runner=runner)
                out["sample_seconds"] = time.time() - t0
    finally:
        runner.close()
    refs = [str(p["answer"]) for p in problems]
    g_eps = [r.extras["episode"] for r in greedy]
    g_right = [r.reward >= 1.0 for r in greedy]
    causes = [cause(e, ref, r.reward, check) for e, ref, r in zip(g_eps, refs, greedy)]
    out.update({
        "greedy_accuracy": sum(g_right) / len(problems),
        "greedy_causes": {c: causes.count(c) / len(problems) for c in CAUSES},
        "behaviour_greedy": behaviour(g_eps, check),
        "greedy_tokens_per_problem": sum(len(r.completion_ids) for r in greedy) / len(problems),
        "examples": _examples(g_eps, refs, causes, problems),
    })
    if sampled:
        per_problem: list[list[tuple[str | None, bool]]] = [[] for _ in problems]
        for r in sampled:
            ep = r.extras["episode"]
            key = answer_key(check(ep["turns"][-1]["text"], refs[r.prompt_index])) \
                if ep["finish"] == "answer" and ep["turns"] else None
            per_problem[r.prompt_index].append((key, r.reward >= 1.0))
        out.update(k_metrics(per_problem, samples))
        out["behaviour_samples"] = behaviour([r.extras["episode"] for r in sampled], check)
        out["sample_tokens_per_sample"] = sum(len(r.completion_ids) for r in sampled) / len(sampled)
    return out


def _examples(eps: list[dict], refs: list[str], causes: list[str], problems: list[dict]) -> dict[str, list]:
    """Up to two greedy episodes of each cause, as transcripts."""
    out: dict[str, list] = collections.defaultdict(list)
    for ep, ref, c, p in zip(eps, refs, causes, problems):
        if len(out[c]) < 2:
            out[c].append({"question": p["prompt"], "answer": ref, "transcript": transcript(ep)})
    return dict(out)


# ----------------------------------------------------------------------------- the GRPO runs
def posttrain(stage: str, recipe: str, output_dir: Path, threads: int, log: Path, overrides: list[str]) -> float:
    took = run_stage([stage, "--recipe", recipe, f"run.output_dir={output_dir}", f"run.threads={threads}",
                      *overrides], log, threads, "reproduce_tools")
    say(f"posttrain {stage} --recipe {recipe}: {took:.0f}s (log {log})")
    return took


def grpo_run(run_dir: Path, check=None) -> dict:
    """Reward, held-out accuracy and time per step from metrics.jsonl; behaviour of the saved training episodes."""
    rows = read_jsonl(run_dir / "metrics.jsonl")
    train = [r for r in rows if "reward/mean" in r]
    evals = {r["step"]: r["eval/accuracy"] for r in rows if "eval/accuracy" in r}
    out = {"steps": [r["step"] for r in train], "reward": [r["reward/mean"] for r in train],
           "step_seconds": [r.get("time/step", 0.0) for r in train],
           "eval_steps": sorted(evals), "eval_accuracy": [evals[s] for s in sorted(evals)],
           "config": read_yaml(run_dir / "config.yaml").get("grpo", {}),
           "env": {k: [r.get(k) for r in train] for k in ("env/tool_calls", "env/valid_calls", "env/called_a_tool",
                                                           "env/sampled_tokens", "env/env_tokens",
                                                           "env/tool_seconds")},
           "completion_length": [r.get("completion/length") for r in train],
           "entropy": [r.get("entropy") for r in train], "zero_var_frac": [r.get("zero_var_frac") for r in train]}
    if check is not None:
        from posttrain.rollout import load_rollouts

        saved = []
        for path in sorted((run_dir / "rollouts").glob("step-*.jsonl")):
            rollouts = load_rollouts(path)
            eps = [r.extras["episode"] for r in rollouts if "episode" in r.extras]
            b = behaviour(eps, check)
            b["step"] = int(path.stem.split("-")[1])
            b["reward"] = sum(r.reward for r in rollouts) / max(1, len(rollouts))
            saved.append(b)
        out["saved_behaviour"] = saved
    return out


# ----------------------------------------------------------------------------- report
def plots(res: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ev, files = res["eval"], []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        fig.savefig(out / name, dpi=100)
        plt.close(fig)
        files.append(name)

    fig, ax = plt.subplots(figsize=(7.5, 4))
    names = [k for k in LABELS if k in ev]
    ax.bar(range(len(names)), [ev[k]["greedy_accuracy"] for k in names],
           color=["0.6", "0.4", "tab:blue", "tab:red", "tab:orange"][:len(names)])
    ax.set_xticks(range(len(names)), [LABELS[k].replace(" (E7 arm)", "\n(E7 arm)").replace(", ", ",\n")
                                      .replace(" with", "\nwith") for k in names], fontsize=8)
    for i, k in enumerate(names):
        ax.text(i, ev[k]["greedy_accuracy"] + 0.01, pct(ev[k]["greedy_accuracy"]), ha="center", fontsize=8)
    ax.set_ylabel(f"held-out greedy accuracy ({res['eval_rows']} problems)")
    ax.set_ylim(0, 1)
    ax.set_title("Word problems with 3-4 digit numbers, SmolLM2-135M-Instruct")
    save(fig, "tools_accuracy.png")

    fig, ax = plt.subplots(figsize=(7, 4))
    for k, color in (("sft", "tab:blue"), ("grpo", "tab:red"), ("instruct", "0.5"), ("grpo_no_tools", "tab:orange")):
        e = ev.get(k, {})
        if "pass_curve" in e:
            ks = list(range(1, len(e["pass_curve"]) + 1))
            ax.plot(ks, e["pass_curve"], "-", color=color, label=f"{LABELS[k]}: pass@K (oracle)")
            ax.plot(list(e["maj_at_k"]), list(e["maj_at_k"].values()), "s--", color=color, label=f"{LABELS[k]}: maj@K")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("samples per problem K")
    ax.set_ylabel("held-out accuracy")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    save(fig, "tools_best_of_k.png")

    g = res["grpo"]
    if g["steps"]:
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot(g["steps"], g["reward"], "o-", color="tab:red", label="training reward (episodes right)")
        if g["eval_steps"]:
            ax.plot(g["eval_steps"], g["eval_accuracy"], "s-", color="k", label="held-out greedy (during training)")
        calls = g["env"]["env/called_a_tool"]
        if any(c is not None for c in calls):
            ax.plot(g["steps"], calls, "^:", color="tab:blue", label="episodes that called a tool")
        nt = res["grpo_no_tools"]
        if nt["eval_steps"]:
            ax.plot(nt["eval_steps"], nt["eval_accuracy"], "s--", color="tab:orange",
                    label="GRPO without tools: held-out greedy")
        ax.set_xlabel("GRPO step")
        ax.set_ylim(0, 1.05)
        ax.legend(fontsize=8)
        save(fig, "tools_training.png")
    return files


def _f(x, spec: str = ".2f") -> str:
    return "n/a" if x is None else format(x, spec)


def report_md(res: dict) -> str:
    ev, sec = res["eval"], res["seconds"]
    L = [f"# Tool-use RL on SmolLM2-135M-Instruct: a calculator on word problems{' (quick smoke run)' if res['quick'] else ''}\n"]
    L.append(f"Runtime: {res['runtime_s'] / 60:.1f} min in all ({res['cpu']}, {os.cpu_count()} cores, load average "
             f"{res['load_average'][0]:.1f} at the start, {res['load_average'][1]:.1f} at the end; torch threads "
             f"{res['threads'] or 'default'}): SFT {sec['sft']:.0f} s, GRPO with tools {sec['grpo']:.0f} s, GRPO "
             f"without tools {sec['grpo_no_tools']:.0f} s, evaluations {sec['eval']:.0f} s"
             + (f" (reused: {', '.join(res['reused'])})" if res["reused"] else "") + ".\n")
    L.append(f"Command: `python scripts/reproduce_tools.py{' --quick' if res['quick'] else ''}"
             f"{''.join(' --set ' + s for s in res['overrides'])}`. Problems: word-math level {DIFFICULTY} (1-2 "
             f"operations on 3-4 digit numbers), {res['eval_rows']} held-out problems (one is "
             f"{100 / res['eval_rows']:.1f} points). Samples: {res['samples']} per problem at T={res['temperature']:g}. "
             f"GRPO budget of both arms: {res['budget']}. Generation: rollout.dtype={res['rollout_dtype']}; "
             f"training: run.mixed_precision={res['mixed_precision']}.\n")
    L.append("## Held-out accuracy\n")
    L.append(f"| model | greedy | one sample (T={res['temperature']:g}) | pass@4 | pass@16 | maj@4 | maj@16 | called a "
             "tool | valid calls | calls / problem |")
    L.append("|---|---|---|---|---|---|---|---|---|---|")
    for k, label in LABELS.items():
        e = ev.get(k)
        if not e:
            continue
        b = e.get("behaviour_greedy", {})
        pk, mk = e.get("pass_at_k", {}), e.get("maj_at_k", {})
        L.append(f"| {label} | **{pct(e['greedy_accuracy'])}** | {pct(pk.get(1))} | {pct(pk.get(4))} | "
                 f"{pct(pk.get(16))} | {pct(mk.get(4))} | {pct(mk.get(16))} | {pct(b.get('called_a_tool'))} | "
                 f"{pct(b.get('valid_call_rate'))} | {_f(b.get('calls_per_episode'))} |")
    own = [k for k in ("sft", "grpo") if f"{k}_own" in ev]
    if own:
        L.append(f"\nOn {res['own']['rows']} word problems in phrasings of our own (`{res['own']['file']}`, written "
                 "apart from the generator's templates, never trained or tuned on), greedy:\n")
        L.append("| model | generator's held-out | phrasings of our own | difference |")
        L.append("|---|---|---|---|")
        for k in own:
            a, b = ev[k]["greedy_accuracy"], ev[f"{k}_own"]["greedy_accuracy"]
            L.append(f"| {LABELS[k]} | {pct(a)} | **{pct(b)}** | {100 * (b - a):+.1f} points |")
    v = res["verdict"]
    L.append("")
    L.append(f"**Target** (GRPO with tools at least 10 points above the start model and above GRPO without tools): "
             f"**{'met' if v['met'] else 'not met'}**: {v['text']}\n")
    L.append(f"**What GRPO itself added** over its start (the SFT model): {v['grpo_over_sft']:+.1f} points greedy.\n")
    L.append(f"**Target of RL over its SFT start** (issue 49; samples at T={res['temperature']}): "
             f"**{'met' if v['rl_met'] else 'not met'}**: {v['rl_text']}\n")
    L.append("## Why the wrong greedy answers are wrong\n")
    L.append("| model | " + " | ".join(CAUSES) + " |")
    L.append("|---|" + "---|" * len(CAUSES))
    for k in ("instruct_tools", "sft", "grpo"):
        if k in ev:
            L.append(f"| {LABELS[k]} | " + " | ".join(pct(ev[k]["greedy_causes"][c]) for c in CAUSES) + " |")
    L.append("\n'wrong expression': every valid call computed something other than the answer (the calculator is "
             "exact, so the model chose the wrong operations or numbers); 'right result ignored': a call returned "
             "the answer and the final answer says another number.\n")
    L.append("## Behaviour\n")
    L.append("| model (greedy episodes) | turns | answered | with a tool error | recovered after it | answer ignores "
             "the last result | sampled tokens | environment tokens | tool s |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for k in ("instruct_tools", "sft", "grpo"):
        if k in ev:
            b = ev[k]["behaviour_greedy"]
            L.append(f"| {LABELS[k]} | {b['turns_per_episode']:.2f} | {pct(b['answered'])} | "
                     f"{pct(b['episodes_with_a_tool_error'])} | {pct(b['recovered_after_error'])} | "
                     f"{pct(b['ignores_last_result'])} | {b['sampled_tokens']:.1f} | {b['env_tokens']:.1f} | "
                     f"{b['tool_seconds']:.4f} |")
    for k, label in (("grpo", "GRPO with tools"), ("grpo_no_tools", "GRPO without tools")):
        spread = _over_training(res[k])
        if spread:
            L.append(f"\n{label} over training: {spread}.")
    saved = res["grpo"].get("saved_behaviour", [])
    if saved:
        L.append("\nTraining episodes over GRPO steps (saved every few steps):\n")
        L.append("| step | reward | called a tool | valid calls | calls | with a tool error | recovered | ignores "
                 "the last result |")
        L.append("|---|---|---|---|---|---|---|---|")
        for b in saved:
            L.append(f"| {b['step']} | {b['reward']:.3f} | {pct(b['called_a_tool'])} | {pct(b['valid_call_rate'])} | "
                     f"{b['calls_per_episode']:.2f} | {pct(b['episodes_with_a_tool_error'])} | "
                     f"{pct(b['recovered_after_error'])} | {pct(b['ignores_last_result'])} |")
    for k in ("sft", "grpo"):
        if k in ev and ev[k].get("examples"):
            L.append(f"\n### Examples, {LABELS[k]} (greedy)\n")
            for c, items in ev[k]["examples"].items():
                for item in items[:1]:
                    L.append(f"- **{c}** (answer {item['answer']}): {item['question']}\n\n```\n{item['transcript']}\n```")
    L.append("\n## Compute\n")
    L.append("| stage | seconds | sequences | tokens sampled | environment tokens | tool seconds |")
    L.append("|---|---|---|---|---|---|")
    for k, label in (("grpo", "GRPO with tools"), ("grpo_no_tools", "GRPO without tools")):
        c = res["compute"][k]
        L.append(f"| {label} | {sec[k]:.0f} | {c['sequences']:.0f} | {c['sampled_tokens']:,.0f} | "
                 f"{_f(c.get('env_tokens'), ',.0f')} | {_f(c.get('tool_seconds'), '.3f')} |")
    L.append(f"| SFT (the demonstrations) | {sec['sft']:.0f} | {res['compute']['sft']['sequences']} | | | |")
    if res.get("stage_plots"):
        L.append("\nEvery stage's metrics (`posttrain plot`): " + ", ".join(
            f"[{name}]({folder}/)" for name, folder in res["stage_plots"].items()) + ".")
    L.append("\n![accuracy](tools_accuracy.png)\n![best-of-K](tools_best_of_k.png)"
             + ("\n![training](tools_training.png)" if "tools_training.png" in res["figures"] else "") + "\n")
    return "\n".join(L) + "\n"


def _over_training(run: dict) -> str:
    """Entropy of the sampled tokens and the share of groups with one reward for all (which train nothing), first
    step / mean / last step; empty when the run logged neither."""
    parts = []
    for key, label, spec in (("entropy", "entropy (nats per sampled token)", ".3f"),
                             ("zero_var_frac", "groups with no reward variance", ".0%")):
        vals = [v for v in run.get(key, []) if v is not None]
        if vals:
            parts.append(f"{label} {format(vals[0], spec)} / {format(sum(vals) / len(vals), spec)} / "
                         f"{format(vals[-1], spec)} (first step / mean / last)")
    return "; ".join(parts)


# Issue 49's target for RL itself, against its own start (the SFT model, on the same problems): greedy at least
# RL_GAIN above it, pass@16 at most PASS_DROP below it, and on the phrasings of our own a gain of at least OWN_GAIN
# (the gain holds on problems the generator did not write; half of RL_GAIN, because one of ~60 problems there is
# ~1.7 points and a difference of two accuracies on them spreads by ~8 points).
RL_GAIN, PASS_DROP, OWN_GAIN = 0.10, 0.03, 0.05
EPS = 1e-9  # 0.75 - 0.65 is 0.0999... in floats


def verdict(ev: dict) -> dict:
    """Issue 35's target (GRPO with tools above the instruct model and above GRPO without tools) and issue 49's
    (GRPO above its SFT start: RL_GAIN greedy, pass@16 within PASS_DROP, OWN_GAIN on the own phrasings), each with
    its numbers; a figure that was not measured (no samples, no own set) fails the second."""
    g = ev["grpo"]["greedy_accuracy"]
    start = max(ev["instruct"]["greedy_accuracy"], ev["instruct_tools"]["greedy_accuracy"])
    nt = ev["grpo_no_tools"]["greedy_accuracy"]
    met = g - start >= 0.10 - EPS and g - nt >= 0.10 - EPS
    text = (f"{pct(g)} against the instruct model's best start {pct(start)} ({100 * (g - start):+.1f} points) and "
            f"GRPO without tools {pct(nt)} ({100 * (g - nt):+.1f} points).")
    gain = g - ev["sft"]["greedy_accuracy"]
    k = max(KS)
    p16 = [(ev[m].get("pass_at_k") or {}).get(k) for m in ("sft", "grpo")]
    drop = None if None in p16 else p16[0] - p16[1]
    sft_own, grpo_own = (ev[m]["greedy_accuracy"] if m in ev else None for m in ("sft_own", "grpo_own"))
    own_gain = None if sft_own is None or grpo_own is None else grpo_own - sft_own
    sampled = [ev[m].get("sample_accuracy") for m in ("sft", "grpo")]
    rl_met = (gain >= RL_GAIN - EPS and drop is not None and drop <= PASS_DROP + EPS and own_gain is not None
              and own_gain >= OWN_GAIN - EPS)
    parts = [f"greedy {pct(ev['sft']['greedy_accuracy'])} -> {pct(g)} ({100 * gain:+.1f} points; at least "
             f"{100 * RL_GAIN:+.0f})",
             f"pass@{k} not measured" if drop is None else
             f"pass@{k} {pct(p16[0])} -> {pct(p16[1])} ({-100 * drop:+.1f} points; at most {100 * PASS_DROP:.0f} down)",
             "phrasings of our own not measured" if own_gain is None else
             f"phrasings of our own {pct(sft_own)} -> {pct(grpo_own)} ({100 * own_gain:+.1f} points; at least "
             f"{100 * OWN_GAIN:+.0f})"]
    rl_text = ", ".join(parts) + ("" if None in sampled else f"; sampled accuracy {pct(sampled[0])} -> "
                                                            f"{pct(sampled[1])}") + "."
    return {"met": met, "text": text, "grpo_over_sft": 100 * gain, "rl_met": rl_met, "rl_text": rl_text}


def compute(res: dict) -> dict:
    out = {}
    for k in ("grpo", "grpo_no_tools"):
        g = res[k]
        P, K = g["config"].get("prompts_per_step", 0), g["config"].get("group_size", 0)
        seqs = P * K * len(g["steps"])
        env = g["env"]
        tok_per_seq = env["env/sampled_tokens"] if any(x is not None for x in env["env/sampled_tokens"]) \
            else g["completion_length"]
        c = {"sequences": seqs, "sampled_tokens": P * K * sum(x or 0.0 for x in tok_per_seq)}
        if any(x is not None for x in env["env/env_tokens"]):
            c["env_tokens"] = P * K * sum(x or 0.0 for x in env["env/env_tokens"])
            c["tool_seconds"] = P * K * sum(x or 0.0 for x in env["env/tool_seconds"])
        out[k] = c
    sft_cfg = res.get("sft_config", {})
    out["sft"] = {"sequences": sft_cfg.get("max_steps", 0) * sft_cfg.get("batch_size", 0)}
    return out


# ----------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a smoke run: short SFT and GRPO, fewer problems and samples")
    ap.add_argument("--out", type=Path, default=None, help="output directory (default runs/tools[-quick])")
    ap.add_argument("--threads", type=int, default=0, help="torch threads per stage and here (0: torch's default)")
    ap.add_argument("--eval-rows", type=int, default=None, help="held-out problems (default 100; --quick 32)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="STAGE.KEY=VALUE",
                    help="override for the smol-tools stages, e.g. grpo.lr=5e-5 (repeatable)")
    ap.add_argument("--fresh", action="store_true", help="redo every stage even when it exists in --out")
    ap.add_argument("--own", default=str(OWN), help="a second held-out set (JSONL: prompt, answer) the SFT and GRPO "
                    "models are scored on greedy; default: the word problems in phrasings of our own; '' skips it")
    args = ap.parse_args(argv)
    out = prepare(args, "reproduce_tools", ROOT / "runs" / ("tools" + ("-quick" if args.quick else "")))
    from dataclasses import asdict

    from posttrain.cli import STAGES
    from posttrain.config import resolve
    from posttrain.models import is_model_dir
    from posttrain.problems import env_problem
    from posttrain.rollout import configure
    from posttrain.runtime import cpu_model
    from posttrain.tasks import load_split
    from posttrain.verifiers.envs import get_env
    from posttrain.verifiers.math_answer import MathVerifier
    from posttrain.verifiers.runner import VerifierPool

    t_all, load_start = time.time(), os.getloadavg()[0]
    overrides = (list(QUICK) if args.quick else []) + args.overrides
    res_t = resolve(TOOLS, "grpo", STAGES["grpo"].load()[0], [f"run.output_dir={out / 'tools'}", *overrides])
    gcfg = res_t.stage_cfg
    budget = [f"grpo.{k}={getattr(gcfg, k)}" for k in BUDGET_KEYS]
    nt_over = [f"task.difficulty={DIFFICULTY}", *budget, f"grpo.eval_every={gcfg.eval_every}",
               f"grpo.eval_rows={gcfg.eval_rows}", "grpo.final_eval_rows=0", "grpo.save_every=0"]
    res_n = resolve(NO_TOOLS, "grpo", STAGES["grpo"].load()[0], [f"run.output_dir={out / 'no-tools'}", *nt_over])
    instruct = Path(res_t.model.path)
    if not is_model_dir(instruct):
        raise SystemExit(f"reproduce_tools: model.path {str(instruct)!r} is not a model directory; fetch the model "
                         f"first: posttrain models fetch smollm2-135m-instruct {instruct}")
    timing = out / "seconds.json"
    seconds = json.loads(timing.read_text()) if timing.is_file() else {}
    reused = []
    dirs = {"sft": out / "tools" / TOOLS / "sft", "grpo": out / "tools" / TOOLS / "grpo",
            "grpo_no_tools": out / "no-tools" / NO_TOOLS / "grpo"}  # <run.output_dir>/<recipe>/<stage>
    stages = (("sft", TOOLS, out / "tools", overrides),
              ("grpo", TOOLS, out / "tools", overrides + ["grpo.final_eval_rows=0",
                                                           f"grpo.save_rollouts_every={max(1, gcfg.max_steps // 5)}"]),
              ("grpo_no_tools", NO_TOOLS, out / "no-tools", nt_over))
    for name, recipe, run_out, over in stages:
        if (dirs[name] / "final").exists() and name in seconds:
            say(f"reusing {dirs[name]}")
            reused.append(name)
            continue
        shutil.rmtree(dirs[name], ignore_errors=True)
        seconds[name] = posttrain(name.split("_")[0], recipe, run_out, args.threads, out / "logs" / f"{name}.log",
                                  over)
        if name == "sft":  # a new SFT model invalidates the GRPO run on the old one
            seconds.pop("grpo", None)
            shutil.rmtree(dirs["grpo"], ignore_errors=True)
        timing.write_text(json.dumps(seconds))

    configure(**asdict(res_t.rollout))  # generation here as in the stages (rollout.dtype)
    n_rows = args.eval_rows or (32 if args.quick else 100)
    samples = 4 if args.quick else max(KS)
    res_t.task.n_eval = max(res_t.task.n_eval, n_rows)
    res_n.task.n_eval = max(res_n.task.n_eval, n_rows)
    tool_rows, plain_rows = load_split(res_t.task, "eval")[:n_rows], load_split(res_n.task, "eval")[:n_rows]
    problems = [env_problem(r) for r in tool_rows]
    for p, r in zip(problems, plain_rows):  # the same problems for every arm
        if p["prompt"] != r["prompt"] or str(p["answer"]) != str(r["answer"]):
            raise SystemExit(f"reproduce_tools: the held-out problems of {TOOLS} and {NO_TOOLS} differ: "
                             f"{p['prompt']!r} vs {r['prompt']!r}")
    own = []
    if args.own:
        own_path = Path(args.own)
        if not own_path.is_file():
            raise SystemExit(f"reproduce_tools: --own {args.own!r} is not a file")
        own = [env_problem(json.loads(line)) for line in own_path.read_text().splitlines() if line.strip()]
    env = get_env(gcfg.env, **gcfg.env_options)
    T = gcfg.temperature
    ev: dict = {}
    t_eval = time.time()
    pool = VerifierPool(workers=1)
    try:
        for name, model_dir in (("instruct", instruct), ("grpo_no_tools", dirs["grpo_no_tools"] / "final")):
            t0 = time.time()
            e = evaluate_model(model_dir, plain_rows, res_n.stage_cfg.max_new_tokens, pool, mode=MODES["real"],
                               temperature=T)
            ev[name] = e  # 16 samples per problem (E7's evaluation) even under --quick: short answers, cheap
            say(f"{LABELS[name]}: greedy {e['greedy_accuracy']:.3f} ({time.time() - t0:.0f}s)")
    finally:
        pool.close()
    for name, model_dir, n in (("instruct_tools", instruct, 0), ("sft", dirs["sft"] / "final", samples),
                               ("grpo", dirs["grpo"] / "final", samples)):
        t0 = time.time()
        ev[name] = evaluate_episodes(model_dir, problems, env, n, T)
        say(f"{LABELS[name]}: greedy {ev[name]['greedy_accuracy']:.3f}, pass@K {ev[name].get('pass_at_k')}, "
            f"maj@K {ev[name].get('maj_at_k')} ({time.time() - t0:.0f}s)")
        if own and name != "instruct_tools":
            t0 = time.time()
            ev[f"{name}_own"] = evaluate_episodes(model_dir, own, env, 0, T)
            say(f"{LABELS[name]}, {len(own)} problems in phrasings of our own: greedy "
                f"{ev[f'{name}_own']['greedy_accuracy']:.3f} ({time.time() - t0:.0f}s)")
    t_eval = time.time() - t_eval

    check = MathVerifier().check
    res = {"quick": args.quick, "overrides": args.overrides, "threads": args.threads, "eval_rows": n_rows,
           "own": {"file": args.own, "rows": len(own)},
           "samples": samples, "temperature": T, "budget": ", ".join(b.removeprefix("grpo.") for b in budget),
           "rollout_dtype": res_t.rollout.dtype, "mixed_precision": res_t.run.mixed_precision, "reused": reused,
           "seconds": {**{k: seconds[k] for k in ("sft", "grpo", "grpo_no_tools")}, "eval": t_eval}, "eval": ev,
           "grpo": grpo_run(dirs["grpo"], check), "grpo_no_tools": grpo_run(dirs["grpo_no_tools"]),
           "sft_config": read_yaml(dirs["sft"] / "config.yaml").get("sft", {})}
    res["verdict"] = verdict(ev)
    res["compute"] = compute(res)
    res["figures"] = plots(res, out)
    from posttrain.plots import plot_runs  # `posttrain plot` of each stage, linked from the report

    res["stage_plots"] = plot_runs({k: dirs[k] for k in ("sft", "grpo", "grpo_no_tools")}, out, say=say)
    res["runtime_s"] = time.time() - t_all + sum(seconds[k] for k in reused)
    res["load_average"], res["cpu"] = (load_start, os.getloadavg()[0]), cpu_model()
    (out / "tools.json").write_text(json.dumps(res, indent=2, default=str))
    (out / "report.md").write_text(report_md(res))
    say(f"{res['verdict']['text']} RL over its SFT start: {res['verdict']['rl_text']} "
        f"Report {out / 'report.md'} ({res['runtime_s'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
