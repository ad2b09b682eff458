"""Task evaluation through the rollout engine: generate on held-out prompts, score with the task's gold metric.

`posttrain eval --recipe tiny-summarize [model=PATH] [reference=PATH]` (the eval stage, `train` below)
prints the task's held-out metrics (tiny-summarize: gold quality, length, fraction in the length band)
and the gold-preference win-rate of the model against a reference model (ties count half).

For the preference trainers (DPO, PPO), task-agnostic: `policy_eval` (the periodic gold / proxy / KL
metrics, logged as gold/<name> for the task's `GOLD_METRICS`) and `compare_with_sft` (the final held-out
comparison with the SFT model, printed and returned for eval.json).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from posttrain.chat import prompt_text


@dataclass
class EvalConfig:
    model: str = ""
    """Model directory to evaluate; empty: the recipe's SFT model (trained first if missing)."""
    reference: str = ""
    """Model directory to compute the gold-preference win-rate against; empty: the untrained base model."""
    rows: int = 200
    """Held-out prompts to evaluate."""
    max_new_tokens: int = 64
    """Generation budget per completion."""


def complete(model, tokenizer, prompts: list[str], *, max_new_tokens: int = 64, greedy: bool = True,
             temperature: float = 1.0, n: int = 1, seed: int = 0, label: str = "[eval] generating") -> list[str]:
    """Completion texts for `prompts` (n per prompt, prompt-major), from the rollout engine; a phase that runs
    long prints its progress with an ETA (`loop.Progress`, under `label`)."""
    from posttrain.loop import Progress
    from posttrain.rollout import SamplingParams, generate

    params = SamplingParams(n=n, max_new_tokens=max_new_tokens, greedy=greedy, temperature=temperature, seed=seed)
    return [r.text for r in generate(model, tokenizer, prompts, params, progress=Progress(label))]


def evaluate_model(task_name: str, model, tokenizer, rows: list[dict[str, Any]], *, max_new_tokens: int = 64,
                   completions: list[str] | None = None) -> dict[str, Any]:
    """The task's metrics of greedy completions on `rows` (which carry `meta`); rows without the task's meta (a
    user's own data) get `reference_metrics` against their reference completions instead."""
    from posttrain import tasks

    task = tasks.get_task(task_name)
    if completions is None:
        completions = complete(model, tokenizer, [r["prompt"] for r in rows], max_new_tokens=max_new_tokens)
    if all(r.get("meta") for r in rows):
        out = dict(task.evaluate([r["meta"] for r in rows], completions))
    else:
        out = reference_metrics([str(r.get("completion", "")) for r in rows], completions)
    out["n"] = len(rows)
    out["_completions"] = completions
    return out


def reference_metrics(references: list[str], completions: list[str]) -> dict[str, float]:
    """Task-free metrics of completions against reference completions: exact match and word-level F1 (after
    lower-casing and splitting on whitespace, SQuAD's F1 without its article and punctuation rules), mean
    length in words and the fraction of empty completions."""
    def f1(ref: str, out: str) -> float:
        r, o = ref.lower().split(), out.lower().split()
        if not r or not o:
            return float(r == o)
        common = sum(min(r.count(w), o.count(w)) for w in set(o))
        if not common:
            return 0.0
        precision, recall = common / len(o), common / len(r)
        return 2 * precision * recall / (precision + recall)

    n = max(1, len(completions))
    return {"exact_match": sum(" ".join(r.split()) == " ".join(c.split()) for r, c in zip(references, completions)) / n,
            "word_f1": sum(f1(r, c) for r, c in zip(references, completions)) / n,
            "mean_length": sum(len(c.split()) for c in completions) / n,
            "frac_empty": sum(not c.strip() for c in completions) / n}


def win_rate(task_name: str, rows: list[dict[str, Any]], candidates: list[str], baselines: list[str]) -> float:
    from posttrain import tasks

    return float(tasks.get_task(task_name).win_rate([r["meta"] for r in rows], candidates, baselines))


def format_comparison(results: dict[str, dict[str, Any]], task_name: str) -> str:
    """A small table: one column per model, one row per numeric metric."""
    names = list(results)
    keys = [k for k in results[names[0]] if not k.startswith("_") and isinstance(results[names[0]][k], (int, float))]
    w = max(len(k) for k in keys) + 2
    lines = [f"[eval] {task_name}: held-out metrics", " " * w + "".join(f"{n:>14}" for n in names)]
    for k in keys:
        lines.append(f"{k:<{w}}" + "".join(f"{_num(results[n].get(k)):>14}" for n in names))
    return "\n".join(lines)


def _num(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4f}"
    return str(v)


# ----------------------------------------------------------------------------- preference training (DPO, PPO)
def compare_policy(task_name: str, model, tokenizer, rows: list[dict[str, Any]], baseline: list[str], *,
                   max_new_tokens: int = 64, proxy=None, gold_length_weight: float = 2.0,
                   completions: list[str] | None = None) -> dict[str, Any]:
    """Gold metrics of `model`'s greedy completions on `rows` (or of the `completions` given), their gold
    win-rate against `baseline` (completions of the same rows, e.g. the SFT model's; ties count half),
    the mean gold reward (`scoring.GoldScorer`) and, with a `proxy` scorer (a reward model), the mean
    proxy reward.
    Returns the task's metrics plus win_rate (and the wins / ties / losses behind it when the task
    has `gold_prefer`), gold_reward, proxy_reward (when a proxy is given) and "_completions"."""
    from posttrain import tasks
    from posttrain.scoring import GoldScorer

    out = evaluate_model(task_name, model, tokenizer, rows, max_new_tokens=max_new_tokens, completions=completions)
    comps = out["_completions"]
    prompts = [r["prompt"] for r in rows]
    metas = [r["meta"] for r in rows]
    out["win_rate"] = win_rate(task_name, rows, comps, baseline)
    task = tasks.get_task(task_name)
    if task.gold_prefer is not None:  # the counts behind the rate: against a strong baseline most are ties
        prefs = [task.gold_prefer(m, c, b) for m, c, b in zip(metas, comps, baseline)]
        out.update(wins=prefs.count(1), ties=prefs.count(0), losses=prefs.count(-1))
    out["gold_reward"] = GoldScorer(task_name, gold_length_weight).score(prompts, comps, metas).mean()
    if proxy is not None:
        out["proxy_reward"] = proxy.score(prompts, comps, metas).mean()
    return out


def kl_to_reference(policy, reference, tokenizer, prompts: list[str], *, max_new_tokens: int = 64, n: int = 1,
                    seed: int = 0, micro_batch_size: int = 32) -> float:
    """KL(policy || reference) per sequence, estimated on the policy's own samples.

    Samples n completions per prompt from the policy at temperature 1 (rollout engine, seeded),
    then returns the mean over samples of sum_t [log pi(y_t) - log pi_ref(y_t)] over completion
    tokens (eos included). That is the Monte-Carlo (k1) estimate of the sequence-level
    KL(pi || pi_ref) = E_{y ~ pi}[log pi(y) / pi_ref(y)], unbiased because y is sampled from pi at
    temperature 1 (greedy completions would give a biased number). log pi comes from the engine
    (`Rollout.policy_logprobs`), log pi_ref from `posttrain.logprobs.batched_logprobs`.
    """
    from posttrain.logprobs import batched_logprobs, masked_sum
    from posttrain.rollout import SamplingParams, collate_rollouts, generate

    rollouts = generate(policy, tokenizer, prompts, SamplingParams(n=n, temperature=1.0, max_new_tokens=max_new_tokens,
                                                                   seed=seed))
    batch = collate_rollouts(rollouts, tokenizer.pad_token_id)
    ref_logps, _ = batched_logprobs(reference, batch, micro_batch_size)  # (B, T)
    per_seq = masked_sum(batch.policy_logprobs - ref_logps, batch.completion_mask, -1)  # (B,)
    return float(per_seq.mean())


def plot_gold_vs_proxy(metrics: list[dict[str, Any]], path, *, title: str = "") -> str:
    """The over-optimisation picture (Gao et al. 2022, "Scaling Laws for Reward Model Overoptimization"):
    gold and proxy (reward model) reward of the policy over training steps, and against sqrt(KL to the
    reference). `metrics`: rows with step, gold/reward, and optionally proxy/reward and kl.
    Writes a PNG at `path`; returns a one-line note (what was written, or why nothing was:
    matplotlib is optional)."""
    rows = [m for m in metrics if "gold/reward" in m]
    if not rows:
        return "no gold reward logged; no plot"
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed (pip install matplotlib); skipped the gold-vs-proxy plot"
    import math

    steps = [m["step"] for m in rows]
    gold = [m["gold/reward"] for m in rows]
    proxy = [m.get("proxy/reward") for m in rows]
    has_proxy = any(p is not None for p in proxy)
    kls = [m.get("kl") for m in rows]
    has_kl = all(k is not None for k in kls)
    fig, axes = plt.subplots(1, 2 if has_kl else 1, figsize=(11 if has_kl else 6, 4), squeeze=False)
    xs = [("step", steps)] + ([("sqrt(KL to reference), nats^0.5", [math.sqrt(max(0.0, k)) for k in kls])]
                              if has_kl else [])
    for ax, (label, x) in zip(axes[0], xs):
        ax.plot(x, gold, "o-", color="tab:green", label="gold reward")
        ax.set_xlabel(label)
        ax.set_ylabel("gold reward", color="tab:green")
        if has_proxy:
            ax2 = ax.twinx()
            ax2.plot(x, [p if p is not None else float("nan") for p in proxy], "s--", color="tab:blue",
                     label="proxy (RM) reward")
            ax2.set_ylabel("proxy (RM) reward", color="tab:blue")
    what = "gold vs proxy (reward model) reward" if has_proxy else "gold reward (no reward model: no proxy curve)"
    fig.suptitle(f"{title}: {what}" if title else what)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return f"wrote {path}"


# ----------------------------------------------------------------------------- DPO / PPO against the SFT model
def gold_metrics(task_name: str, r: dict[str, Any]) -> dict[str, float]:
    """The logged gold metrics of a `compare_policy` result: gold/reward, gold/<name> for each of the task's
    GOLD_METRICS, gold/win_rate, and proxy/reward when a proxy scored it."""
    from posttrain import tasks

    task = tasks.get_task(task_name)
    m = {"gold/reward": r["gold_reward"]}
    m.update({f"gold/{name}": r[key] for name, key in task.GOLD_METRICS.items() if key in r})
    m["gold/win_rate"] = r["win_rate"]
    if "proxy_reward" in r:
        m["proxy/reward"] = r["proxy_reward"]
    return m


def policy_eval(task_name: str, policy, reference, tokenizer, rows: list[dict[str, Any]], baseline: list[str], *,
                max_new_tokens: int = 64, proxy=None, seed: int = 0) -> dict[str, float]:
    """A preference-trained policy's periodic evaluation on held-out `rows`: `gold_metrics` of its greedy
    completions against the `baseline` completions (the SFT model's), and its KL to `reference`
    (`kl_to_reference`, seeded)."""
    r = compare_policy(task_name, policy, tokenizer, rows, baseline[: len(rows)], max_new_tokens=max_new_tokens,
                       proxy=proxy)
    m = gold_metrics(task_name, r)
    m["kl"] = kl_to_reference(policy, reference, tokenizer, [x["prompt"] for x in rows],
                              max_new_tokens=max_new_tokens, seed=seed)
    return m


def compare_with_sft(stage: str, task_name: str, policy, reference, tokenizer, rows: list[dict[str, Any]],
                     baseline: list[str], *, max_new_tokens: int = 64, proxy=None, seed: int = 0,
                     say: Callable[[str], None] = print) -> dict[str, Any]:
    """The final held-out comparison of a `stage` policy (dpo, ppo) with the SFT model whose greedy completions
    are `baseline`: every task metric, gold reward, win-rate (wins / ties / losses), proxy reward, KL to the
    reference; printed as a table plus the headline lines, and returned for eval.json
    ({"sft": ..., stage: ..., "samples": the first 10 prompts with both completions})."""
    from posttrain import tasks

    base = baseline[: len(rows)]
    sft_m = compare_policy(task_name, None, tokenizer, rows, base, proxy=proxy, completions=base)
    new_m = compare_policy(task_name, policy, tokenizer, rows, base, max_new_tokens=max_new_tokens, proxy=proxy)
    new_m["kl"] = kl_to_reference(policy, reference, tokenizer, [r["prompt"] for r in rows],
                                  max_new_tokens=max_new_tokens, seed=seed)
    sft_m["kl"] = 0.0
    say(format_comparison({"sft": sft_m, stage: new_m}, task_name))
    shown = [("gold reward", "gold_reward")] + list(tasks.get_task(task_name).GOLD_METRICS.items())
    say(f"[{stage}] " + ", ".join(f"{name} {sft_m[key]:.3f} -> {new_m[key]:.3f}" for name, key in shown if key in new_m)
        + f", KL to SFT {new_m['kl']:.2f} nats")
    counts = f": {new_m['wins']} wins, {new_m['ties']} ties, {new_m['losses']} losses" if "wins" in new_m else ""
    say(f"[{stage}] gold win-rate of the {stage.upper()} model against the SFT model: {new_m['win_rate']:.3f} "
        f"({len(rows)} held-out prompts{counts}; ties count half)")
    return {"sft": {k: v for k, v in sft_m.items() if not k.startswith("_")},
            stage: {k: v for k, v in new_m.items() if not k.startswith("_")},
            "samples": [{"prompt": prompt_text(r["prompt"])[-200:], "sft": b, stage: c}
                        for r, b, c in zip(rows[:10], base, new_m["_completions"])]}


# ----------------------------------------------------------------------------- the eval stage
def train(res, ensure) -> Path:
    """`posttrain eval`: the task's held-out metrics of a model and its gold win-rate against a reference model."""
    from posttrain import loop, runtime, tasks
    from posttrain.models import load_model, load_tokenizer

    cfg: EvalConfig = res.stage_cfg
    rows = tasks.load_split(res.task, "eval")[: cfg.rows]
    model_dir = Path(cfg.model) if cfg.model else ensure("sft")
    ref_dir = Path(cfg.reference) if cfg.reference else ensure("base")
    device = runtime.default_device()
    tok = load_tokenizer(model_dir, res.model)
    model = load_model(model_dir, res.model.dtype, device=device)
    ref_tok = load_tokenizer(ref_dir, res.model)
    ref = load_model(ref_dir, res.model.dtype, device=device)
    print(f"[eval] model {model_dir} vs reference {ref_dir} on {len(rows)} held-out prompts of {res.task.name}")
    m = evaluate_model(res.task.name, model, tok, rows, max_new_tokens=cfg.max_new_tokens)
    r = evaluate_model(res.task.name, ref, ref_tok, rows, max_new_tokens=cfg.max_new_tokens)
    m["win_rate_vs_reference"] = win_rate(res.task.name, rows, m["_completions"], r["_completions"])
    r["win_rate_vs_reference"] = 0.5
    print(format_comparison({"model": m, "reference": r}, res.task.name))
    out_dir = res.stage_dir()
    loop.write_json(out_dir / "eval.json", {"model": str(model_dir), "reference": str(ref_dir),
                                            "metrics": {k: v for k, v in m.items() if not k.startswith("_")},
                                            "reference_metrics": {k: v for k, v in r.items() if not k.startswith("_")}})
    return out_dir / "eval.json"
