"""word-calc: word-math problems with 3-5 digit numbers, solved with the calculator (the `calc-words` environment).

CPU:  posttrain grpo --recipe smol-tools     (SmolLM2-135M-Instruct: SFT on these demonstrations, then multi-turn
                                             GRPO in calc-words; see the recipe header)

Pure Python (no torch). The problems are word-math's (`posttrain.tasks.wordmath`, levels 4-5 by default 4: 1-2
operations on 3-4 digit numbers); this module turns each into a tool-use demonstration for SFT:
- the environment's system message (the tools' JSON schemas and the call format), the question, an assistant turn
  that calls the calculator with the problem's whole expression ("1068+806-131", "110*25+1016", "(1632-935)/7"),
  the tool's result, and the answer in prose ("1068 + 806 - 131 = 1743. The answer is 1743.");
- one demonstration in eight first makes a call the calculator refuses (a word or sign its strict grammar does
  not take: "1068 plus 806", "110 × 25", "1632 − 935"), gets the error back, and calls again correctly.
`answer` is the reference; GRPO and evaluation take the question (the first user message) as the problem and let
the environment build the conversation again. Splits and difficulty are word-math's (`task.difficulty` 4 or 5).
"""
from __future__ import annotations

from typing import Any, Literal, Sequence

from posttrain.tasks import wordmath
from posttrain.tasks.calc import refused_call
from posttrain.verifiers.envs.base import format_tool_call
from posttrain.verifiers.envs.calc import WordCalcEnv, calculator

NAME = "word-calc"
VERIFIER = None  # the reward is the environment's (grpo.env: calc-words)
ENV = "calc-words"
GOLD_METRICS = {"accuracy": "accuracy"}
gold_quality = gold_breakdown = gold_key = gold_prefer = win_rate = None
DIFFICULTIES = (4, 5)
DEFAULT_DIFFICULTY = 4
RECOVERY_EVERY = 8  # one demonstration in this many makes a bad call first


def expression(ops: Sequence[Sequence[Any]]) -> str:
    """The calculator expression of word-math's operations ([["=", 1068], ["+", 806], ["-", 131]] -> "1068+806-131";
    a share divides everything before it)."""
    expr = str(ops[0][1])
    for op, n in ops[1:]:
        expr = f"({expr})/{n}" if op == "/" else f"{expr}{op}{n}"
    return expr


def _spaced(expr: str) -> str:
    for op in "+-*/":
        expr = expr.replace(op, f" {op} ")
    return expr


def _bad_spelling(expr: str, k: int) -> str:
    """A spelling of `expr` the calculator refuses (a word or a typographic sign)."""
    for op, bad in (("*", " × "), ("-", " − "), ("+", " plus ")):
        if op in expr and k % 3 == "*-+".index(op):
            return expr.replace(op, bad)
    return expr.replace("+", " plus ").replace("-", " minus ").replace("*", " times ").replace("/", " over ")


def demonstration(problem: dict[str, Any], recover: bool, k: int = 0) -> list[dict[str, Any]]:
    """The conversation of one problem row solved with the tool (after a refused call first when `recover`)."""
    env = WordCalcEnv()
    messages = env.reset({"prompt": problem["prompt"]})
    expr = expression(problem["meta"]["ops"])
    result = calculator(expr)
    if result != str(problem["answer"]):
        raise AssertionError(f"word-calc: {expr} = {result}, not the row's answer {problem['answer']}")
    if recover:
        messages += refused_call(_bad_spelling(expr, k))
    shown = _spaced(expr)
    messages += [{"role": "assistant", "content": format_tool_call("calculator", {"expression": expr})},
                 {"role": "tool", "content": result},
                 {"role": "assistant", "content": f"{shown} = {result}. The answer is {result}."}]
    return messages


def make_examples(n: int, seed: int, split: Literal["train", "eval"],
                  difficulty: int = DEFAULT_DIFFICULTY) -> list[dict[str, Any]]:
    """`n` rows of `split`: {"messages", "train_from", "prompt" (the messages before the answer), "completion" (the
    answer), "answer", "meta": word-math's meta with "reference" and "expression"}."""
    if difficulty not in DIFFICULTIES:
        raise ValueError(f"word-calc difficulty must be one of {', '.join(map(str, DIFFICULTIES))}, got {difficulty!r}")
    out = []
    for k, row in enumerate(wordmath.make_examples(n, seed, split, difficulty)):
        messages = demonstration(row, recover=k % RECOVERY_EVERY == RECOVERY_EVERY - 1, k=k)
        meta = {**row["meta"], "task": NAME, "reference": row["answer"], "expression": expression(row["meta"]["ops"])}
        out.append({"messages": messages, "train_from": 0, "prompt": messages[:-1],
                    "completion": messages[-1]["content"], "answer": row["answer"], "meta": meta})
    return out


def corpus(n: int, seed: int) -> list[str]:
    """Tokenizer texts (a preset built from scratch): the demonstrations' messages, joined."""
    return ["\n".join(m["content"] for m in r["messages"]) for r in make_examples(n, seed, "train")]


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    """Accuracy of final answers by the environment's rule (the math verifier; no copied tool message)."""
    env = WordCalcEnv()
    scores = [env.score({"answer": m["reference"]}, c)[0] for m, c in zip(metas, completions)]
    return {"accuracy": sum(scores) / max(1, len(scores))}
