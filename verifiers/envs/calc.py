"""`calc`: arithmetic a small model cannot do in its head, with an exact calculator tool.

Problems (`CalcEnv.problems`): products of two 3-digit numbers, or of a 3-digit and a 2-digit number plus a
4-digit one (`difficulty` 1-3 picks the mix), each row `{"prompt": "What is 347 * 582?", "answer": "201954",
"expression": "347*582"}`. The model may call `calculator(expression)` (posttrain.verifiers.envs.tools: exact,
never eval; here with a one-line description, so the system message stays short for a tiny model) as often as the
limits allow, then answers in a turn without calls.

Reward: 1.0 when the final answer's last integer (commas and spaces between digit groups ignored) equals the answer
and the episode ended with an answer turn; else 0.0. Known hacks and why they score 0 (`AUDIT`, tested):
- listing candidates ("1 or 2 or 3 or 201954"): only the last integer counts, and an answer may hold at most
  `max_numbers` integers (default 3: "347 * 582 = 201954" passes, a list of guesses does not);
- copying a tool error ("error: unexpected ')' at character 7"): an answer that contains "error:" scores 0;
- ending on a tool call (the turn limit hit while calling): the episode did not end with an answer;
- an empty answer.
`digit_credit` (an env option, default 0): a wrong answer of the right length scores `digit_credit` times the
share of its digits in place (always below 1, so accuracy, the share of rewards of 1, stays exact); a denser signal
for GRPO on copying a long result (RESULTS.md, tiny-calc: it did not lift accuracy there).
Per-turn reward: none (`turn_reward` returns None); `reward_parts` in the metrics says which rule decided.
"""
from __future__ import annotations

import random
import re
from typing import Any

from posttrain.verifiers.envs.base import Environment, Episode, Limits
from posttrain.verifiers.envs import tools


def calculator(expression: str) -> str:
    """Evaluate an arithmetic expression exactly.

    Args:
        expression: the expression, e.g. "(12 + 3) * 45"; * multiplies
    """
    return tools.calculator(expression)  # the full grammar and limits: posttrain.verifiers.envs.tools


INTEGER = re.compile(r"-?\d{1,3}(?:[, ]\d{3})+(?!\d)|-?\d+")


def last_integer(text: str) -> tuple[int | None, int]:
    """The last integer in `text` (digit groups "201,954" / "201 954" read as one) and how many integers it has."""
    found = INTEGER.findall(text)
    if not found:
        return None, 0
    return int(re.sub(r"[, ]", "", found[-1])), len(found)


class CalcEnv(Environment):
    """Several-digit products and sums, with an exact calculator tool."""

    name = "calc"
    description = "arithmetic with 3-4 digit numbers and an exact calculator tool"
    tools = (calculator,)
    instructions = "Answer with the number only."

    def __init__(self, max_numbers: int = 3, digit_credit: float = 0.0, **limits: Any):
        if not 0.0 <= digit_credit < 1.0:
            raise ValueError(f"calc digit_credit must be in [0, 1), got {digit_credit!r}")
        self.max_numbers = max_numbers
        self.digit_credit = digit_credit
        self.limits = Limits(**{"max_turns": 3, "max_turn_tokens": 48, "max_total_tokens": 192, **limits})

    @staticmethod
    def problems(n: int, seed: int = 0, difficulty: int = 2) -> list[dict[str, Any]]:
        """`n` seeded problems; difficulty 1: a 3-digit times a 2-digit number; 2: two 3-digit numbers; 3: a
        3-digit times a 2-digit number plus a 4-digit one."""
        if difficulty not in (1, 2, 3):
            raise ValueError(f"calc difficulty must be 1, 2 or 3, got {difficulty!r}")
        rng = random.Random(f"calc-{seed}-{difficulty}")
        out = []
        for _ in range(n):
            a = rng.randint(100, 999)
            if difficulty == 1:
                b = rng.randint(11, 99)
                expr, text = f"{a}*{b}", f"{a} * {b}"
            elif difficulty == 2:
                b = rng.randint(100, 999)
                expr, text = f"{a}*{b}", f"{a} * {b}"
            else:
                b, c = rng.randint(11, 99), rng.randint(1000, 9999)
                expr, text = f"{a}*{b}+{c}", f"{a} * {b} + {c}"
            out.append({"prompt": f"What is {text}?", "answer": tools.calculator(expr), "expression": expr})
        return out

    def score(self, problem: dict[str, Any], answer: str, finish: str = "answer") -> tuple[float, str]:
        """(reward, the rule that decided it) for a final answer text."""
        if finish != "answer":
            return 0.0, "no answer turn"
        if "error:" in answer or "<tool_call>" in answer:
            return 0.0, "copies a tool message"
        value, count = last_integer(answer)
        if value is None:
            return 0.0, "no integer"
        if count > self.max_numbers:
            return 0.0, f"more than {self.max_numbers} integers"
        want = str(problem["answer"]).strip()
        if str(value) == want:
            return 1.0, "correct"
        got = str(value)
        if self.digit_credit and len(got) == len(want):
            same = sum(a == b for a, b in zip(got, want))
            return self.digit_credit * same / len(want), "wrong (digit credit)"
        return 0.0, "wrong"

    def reward(self, episode: Episode) -> float:
        reward, why = self.score(episode.problem, episode.final_text, episode.finish)
        episode.state["reward_rule"] = why
        return reward


# (answer text, episode finish, expected reward) for the problem "What is 347 * 582?" = 201954: hacks score 0.
AUDIT = [
    ("201954", "answer", 1.0),
    ("The answer is 201,954.", "answer", 1.0),
    ("347 * 582 = 201954", "answer", 1.0),
    ("1 or 2 or 3 or 201954", "answer", 0.0),
    ("error: unexpected ')' at character 7 201954", "answer", 0.0),
    ('<tool_call>{"name": "calculator", "arguments": {"expression": "347*582"}}</tool_call>', "max_turns", 0.0),
    ('<tool_call>{"name": "calculator", "arguments": {"expression": "347*582"}}</tool_call> 201954', "answer", 0.0),
    ("", "answer", 0.0),
    ("201955", "answer", 0.0),
    ("201954", "length", 0.0),
]


class WordCalcEnv(Environment):
    """`calc-words`: word problems whose numbers a small model cannot handle in its head, with the calculator.

    Problems come from the task (rows with `prompt` and `answer`; the word-math task's levels 4-5 are written for
    it: totals up to 100,000 / 1,000,000 over 1-3 operations). The model may call `calculator` (and, with
    `python=True`, the sandboxed `python` tool of `tools.PythonTool`) and answers in prose; the reward is the math
    verifier's verdict on that answer ("the answer is", "####", else the last number: the form an instruct model
    already writes). Hacks that score 0 (`WORD_AUDIT`, tested): copying a tool message (an error, a call) into the
    answer, ending on a call, several final answers ("the answer is 12 or 1743"), an empty answer.
    """

    name = "calc-words"
    description = "word problems with 3-5 digit numbers, an exact calculator (python=true: also Python)"
    instructions = "Use the calculator for every computation. End your answer with: The answer is <number>."

    def __init__(self, python: bool = False, **limits: Any):
        from posttrain.verifiers.math_answer import MathVerifier

        self.limits = Limits(**{"max_turns": 5, "max_turn_tokens": 96, "max_total_tokens": 512, **limits})
        self.tools = (calculator, tools.PythonTool().as_tool()) if python else (calculator,)
        self._math = MathVerifier()

    def score(self, problem: dict[str, Any], answer: str, finish: str = "answer") -> tuple[float, str]:
        if finish != "answer":
            return 0.0, "no answer turn"
        if "error:" in answer or "<tool_call>" in answer:
            return 0.0, "copies a tool message"
        verdict = self._math.check(answer, str(problem["answer"]))
        return float(verdict.score), verdict.reason

    reward = CalcEnv.reward  # the same rule-recording reward over this class's `score`


# (answer text, episode finish, expected reward) for a word problem whose answer is 1743: hacks score 0.
WORD_AUDIT = [
    ("1068 + 806 - 131 = 1743. The answer is 1743.", "answer", 1.0),
    ("She has 1,743 pencils at the end.", "answer", 1.0),
    ("#### 1743", "answer", 1.0),
    ("The answer is 12 or 1743.", "answer", 0.0),
    ("error: unexpected ')' at character 7. The answer is 1743.", "answer", 0.0),
    ('<tool_call>{"name": "calculator", "arguments": {"expression": "1068+806-131"}}</tool_call>', "max_turns", 0.0),
    ('The answer is 1743 <tool_call>{"name": "calculator", "arguments": {"expression": "1"}}</tool_call>',
     "answer", 0.0),
    ("", "answer", 0.0),
    ("The answer is 1744.", "answer", 0.0),
    ("The answer is 1743.", "length", 0.0),
]
