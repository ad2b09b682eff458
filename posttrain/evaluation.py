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
