"""tiny-calc: products and sums of 3-4 digit numbers, solved with the calculator tool (the `calc` environment).

CPU:  posttrain grpo --recipe tiny-calc     (tokenizer, tiny model, SFT on tool-use demonstrations, then multi-turn
                                            GRPO in the calc environment; see the recipe header)

Pure Python (no torch). The problems, the tool and the reward are the environment's
(`posttrain.verifiers.envs.calc`); this module turns them into rows:
- every row is a conversation (`messages`, TRL's format): the environment's system message (the tool's JSON schema
  and the call format), the question, an assistant turn that calls the calculator, the tool's answer, and the final
  answer. About one demonstration in eight first makes a malformed call (`347 x 582`, `347×582`: the calculator's
  strict grammar refuses them), gets the error back, and calls again correctly: the model sees a recovery.
  `task.options.tool_rate` (the recipe: 0.4) keeps that share of the training demonstrations and has the others
  answer at once ("Answer: 673736"), so the SFT model knows the call but mostly answers in its head; GRPO's reward
  then teaches it to call (RESULTS.md, Recipes > tiny-calc).
- `answer` (the exact result) is the reference; GRPO and evaluation take the question (the first user message) as
  the problem and let the environment build the conversation again.
- Splits: a SHA-1 of the expression sends about 20% of problems to "eval"; `make_examples` is deterministic.
`difficulty` of the environment's generator: 2 (two 3-digit numbers) for SFT and evaluation, which a 1M-parameter
model cannot multiply in its head.
"""
from __future__ import annotations

import hashlib
from typing import Any, Literal, Sequence

from posttrain.errors import ConfigError
from posttrain.verifiers.envs.base import format_tool_call
from posttrain.verifiers.envs.calc import CalcEnv, calculator, last_integer

NAME = "tiny-calc"
VERIFIER = None  # the reward is the environment's (grpo.env: calc)
ENV = "calc"
GOLD_METRICS = {"accuracy": "accuracy"}
gold_quality = gold_breakdown = gold_key = gold_prefer = win_rate = None
DIFFICULTY = 2
EVAL_FRACTION = 0.2
RECOVERY_EVERY = 8  # one demonstration in this many makes a bad call first
OPTIONS = {"tool_rate": "fraction of the training demonstrations that call the calculator (0-1, default 1); the "
                        "others answer at once (\"Answer: N\"), as a demonstrator sure of its arithmetic"}
DIRECT_PREFIX = "Answer: "  # a direct answer's first token differs from a call's: calling or not is one choice


def _split_of(expression: str) -> str:
    h = int(hashlib.sha1(expression.encode()).hexdigest()[:8], 16)
    return "eval" if h % 1000 < EVAL_FRACTION * 1000 else "train"


def _uses_tool(expression: str, tool_rate: float) -> bool:
    """Whether the demonstration of `expression` calls the calculator: a hash of the expression (salted apart
    from the split's), so a problem keeps its kind whatever n, seed and the other rows."""
    h = int(hashlib.sha1(b"tool:" + expression.encode()).hexdigest()[:8], 16)
    return h % 10_000 < tool_rate * 10_000


def _bad_spelling(expression: str, k: int) -> str:
    return expression.replace("*", [" x ", "×", " times "][k % 3])


def refused_call(bad: str) -> list[dict[str, Any]]:
    """A calculator call with an expression its grammar refuses, and the error message it gets back."""
    try:
        calculator(bad)
    except ValueError as e:
        return [{"role": "assistant", "content": format_tool_call("calculator", {"expression": bad})},
                {"role": "tool", "content": f"error: ValueError: {e}"}]
    raise AssertionError(f"the calculator accepted {bad!r}")


def demonstration(problem: dict[str, Any], recover: bool, k: int = 0, tool: bool = True) -> list[dict[str, Any]]:
    """The conversation of one problem solved with the tool (after a refused call first when `recover`), or
    answered at once without it (`tool=False`)."""
    env = CalcEnv()
    messages = env.reset(problem)
    if not tool:
        return messages + [{"role": "assistant", "content": DIRECT_PREFIX + problem["answer"]}]
    if recover:
        messages += refused_call(_bad_spelling(problem["expression"], k))
    messages += [{"role": "assistant", "content": format_tool_call("calculator", {"expression": problem["expression"]})},
                 {"role": "tool", "content": calculator(problem["expression"])},
                 {"role": "assistant", "content": problem["answer"]}]
    return messages


def make_examples(n: int, seed: int, split: Literal["train", "eval"], tool_rate: float = 1.0) -> list[dict[str, Any]]:
    """`n` rows of `split`: {"messages", "train_from", "prompt" (the messages before the answer), "completion" (the
    answer), "answer", "meta": {"task", "reference", "expression", "tool"}}. A fraction `tool_rate` of the training
    rows calls the calculator (about one in RECOVERY_EVERY of those after a refused call), the rest answer at once;
    every held-out row calls it (SFT's evaluation then scores the answer after the tool's result)."""
    if isinstance(tool_rate, bool) or not isinstance(tool_rate, (int, float)) or not 0 <= tool_rate <= 1:
        raise ConfigError(f"task.options.tool_rate: a fraction from 0 to 1, got {tool_rate!r}")
    out: list[dict[str, Any]] = []
    seen: set[str] = set()
    tool_rows = 0
    batch = 0
    while len(out) < n:
        for p in CalcEnv.problems(4 * n + 64, seed=seed * 1000 + batch, difficulty=DIFFICULTY):
            if p["expression"] in seen or _split_of(p["expression"]) != split:
                continue
            seen.add(p["expression"])
            tool = split == "eval" or _uses_tool(p["expression"], tool_rate)
            k = tool_rows
            tool_rows += tool
            messages = demonstration(p, recover=tool and k % RECOVERY_EVERY == RECOVERY_EVERY - 1, k=k, tool=tool)
            # the shape posttrain.data gives a conversational SFT row: every assistant turn trained
            out.append({"messages": messages, "train_from": 0, "prompt": messages[:-1],
                        "completion": messages[-1]["content"], "answer": p["answer"],
                        "meta": {"task": NAME, "reference": p["answer"], "expression": p["expression"],
                                 "tool": tool}})
            if len(out) == n:
                break
        batch += 1
    return out


def problem_of(row: dict[str, Any]) -> dict[str, Any]:
    """The environment's problem for a row: its question (first user message) and answer."""
    if "messages" in row:
        question = next(m["content"] for m in row["messages"] if m["role"] == "user")
    else:
        question = row["prompt"]
    return {"prompt": question, "answer": str(row["answer"]), "expression": row.get("meta", {}).get("expression")}


def corpus(n: int, seed: int) -> list[str]:
    """Tokenizer texts: the demonstrations' messages, joined."""
    return ["\n".join(m["content"] for m in r["messages"]) for r in make_examples(n, seed, "train")]


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    """Accuracy of final answers (the environment's rule: the last integer, at most 3 integers, no copied tool
    message)."""
    env = CalcEnv()
    scores = [env.score({"answer": m["reference"]}, c)[0] for m, c in zip(metas, completions)]
    return {"accuracy": sum(scores) / max(1, len(scores)),
            "has_integer": sum(last_integer(c)[0] is not None for c in completions) / max(1, len(completions))}
