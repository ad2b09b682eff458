"""Task evaluation through the rollout engine: generate on held-out prompts, score with the task's gold metric.

`posttrain eval --recipe tiny-summarize [model=PATH] [reference=PATH]` prints:
gold quality, length, fraction in the length band, and the gold-preference win-rate of
the model against a reference model (ties count half).
"""
from __future__ import annotations

from typing import Any


def complete(model, tokenizer, prompts: list[str], *, max_new_tokens: int = 64, greedy: bool = True,
             temperature: float = 1.0, n: int = 1, seed: int = 0) -> list[str]:
    """Completion texts for `prompts` (n per prompt, prompt-major), from the rollout engine."""
    from posttrain.rollout import SamplingParams, generate

    params = SamplingParams(n=n, max_new_tokens=max_new_tokens, greedy=greedy, temperature=temperature, seed=seed)
    return [r.text for r in generate(model, tokenizer, prompts, params)]


def evaluate_model(task_name: str, model, tokenizer, rows: list[dict[str, Any]], *, max_new_tokens: int = 64,
                   completions: list[str] | None = None) -> dict[str, Any]:
    """The task's metrics of greedy completions on `rows` (which carry `meta`)."""
    from posttrain import tasks

    task = tasks.get_task(task_name)
    if completions is None:
        completions = complete(model, tokenizer, [r["prompt"] for r in rows], max_new_tokens=max_new_tokens)
    out = dict(task.evaluate([r["meta"] for r in rows], completions))
    out["n"] = len(rows)
    out["_completions"] = completions
    return out


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
    if hasattr(task, "gold_prefer"):  # the counts behind the rate: against a strong baseline most are ties
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
