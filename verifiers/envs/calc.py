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
for GRPO on copying a long result (docs/results-archive.md, tiny-calc first runs: it did not lift
accuracy there).
Per-turn reward: none (`turn_reward` returns None).
"""
from __future__ import annotations

import random
import re
from fractions import Fraction
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


MAX_ANSWER_DIGITS = 1000  # a longer last integer is no answer (and Python's int() refuses more than 4300 digits)


def last_integer(text: str) -> tuple[int | None, int]:
    """The last integer in `text` (digit groups "201,954" / "201 954" read as one) and how many integers it has;
    None for the integer when there is none, or when it has more than MAX_ANSWER_DIGITS digits."""
    found = INTEGER.findall(text)
    if not found:
        return None, 0
    digits = re.sub(r"[, ]", "", found[-1])
    return (int(digits) if len(digits.lstrip("-")) <= MAX_ANSWER_DIGITS else None), len(found)


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
            return 0.0, "no integer" if count == 0 else f"an integer of more than {MAX_ANSWER_DIGITS} digits"
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

    `partial_credit` (an env option, default 0; ToolRL, arXiv 2504.13958, found partial credit on the call better
    than exact match at 1.5B): an episode that ends with a wrong answer turn scores `partial_credit` times the mean
    of three parts of its calculator calls (`credit_parts`), always below 1, so accuracy (the share of rewards of 1)
    stays exact. Each part is written against its obvious hack (`PARTIAL_AUDIT`, tested):
    - `call`: some call ran (no error) on an expression holding one of the problem's numbers. Hack: any valid call
      ("1+1") earns it; it needs a number of the problem.
    - `numbers`: the problem's numbers its valid calls use, over the problem's count plus every number they make
      up (neither in the problem, nor a result of an earlier call, nor a problem number used more often than the
      problem has it). Hack: padding an expression with numbers of its own ("1068+806-131+5") lowers it;
      writing every number of the problem with the wrong operations earns it, and no `value` part.
    - `value`: the share of valid calls whose result is a running total of the problem (an intermediate or the
      answer: `meta.ops` where the row has them, else the answer alone). Hack: fishing with many calls over the
      problem's numbers: every call that misses lowers the share, and every reuse of a number lowers `numbers`.
    A copied tool message, a turn limit hit and no calls at all score 0, as without partial credit.
    Metrics (`metrics`; the trainers log them as `env/<name>`): `reward_parts/call`, `/numbers`, `/value`, each part's
    mean over the wrong answers scored with partial credit, and `partial_credit`, the share of those that earned some.
    """

    name = "calc-words"
    description = ("word problems with 3-5 digit numbers, an exact calculator (python=true: also Python; "
                   "partial_credit=W: part credit for the calls)")
    instructions = "Use the calculator for every computation. End your answer with: The answer is <number>."

    def __init__(self, python: bool = False, partial_credit: float = 0.0, **limits: Any):
        from posttrain.verifiers.math_answer import MathVerifier

        if not isinstance(partial_credit, (int, float)) or not 0.0 <= partial_credit < 1.0:
            raise ValueError(f"calc-words partial_credit must be in [0, 1), got {partial_credit!r}")
        self.partial_credit = float(partial_credit)
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

    def reward(self, episode: Episode) -> float:
        reward, why = self.score(episode.problem, episode.final_text, episode.finish)
        if self.partial_credit and reward < 1.0 and why not in ("no answer turn", "copies a tool message"):
            parts = credit_parts(episode.problem, episode.tool_results())
            episode.state["reward_parts"] = parts
            share = sum(parts.values()) / len(parts)
            if share > 0:
                reward, why = self.partial_credit * share, "wrong (partial credit)"
        episode.state["reward_rule"] = why
        return reward

    def metrics(self, episode: Episode) -> dict[str, float]:
        """With partial credit, for a wrong answer: each credit part's value and whether any credit was given."""
        parts = episode.state.get("reward_parts")
        if parts is None:
            return {}
        return {**{f"reward_parts/{k}": float(v) for k, v in parts.items()},
                "partial_credit": float(episode.state.get("reward_rule") == "wrong (partial credit)")}


NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _value(text: str) -> Fraction | None:
    """A calculator result ("1743", "2.5", "7/3 (≈ 2.33333333333)") or a number as an exact fraction; None if neither."""
    try:
        return Fraction(str(text).split(" (", 1)[0].replace(",", "").strip())
    except (ValueError, ZeroDivisionError):
        return None


def running_totals(problem: dict[str, Any]) -> set[Fraction]:
    """The right values of a problem: the running totals of its `meta.ops` (word-math's [[op, n], ...]) after each
    operation, the answer among them; without ops, the answer alone."""
    answer = _value(problem.get("answer", ""))
    out = {answer} if answer is not None else set()
    meta = problem.get("meta") if isinstance(problem.get("meta"), dict) else {}
    total = None
    for op, n in meta.get("ops") or []:
        n = Fraction(n)
        if op == "=" or total is None:
            total = n
        elif op == "+":
            total += n
        elif op == "-":
            total -= n
        elif op == "*":
            total *= n
        elif op == "/" and n:
            total /= n
        else:
            return out
        out.add(total)
    return out


def credit_parts(problem: dict[str, Any], results: list) -> dict[str, float]:
    """The three partial-credit parts of an episode's calculator calls (`WordCalcEnv`'s docstring): call, numbers,
    value, each in [0, 1]. `results` are the episode's `ToolResult`s in order."""
    given = [_value(n) for n in INTEGER.findall(str(problem.get("prompt", "")))]
    given = [g for g in given if g is not None]
    right = running_totals(problem)
    valid = [r for r in results if r.error is None and r.call.name == "calculator"
             and isinstance((r.call.arguments or {}).get("expression"), str)]
    used: list[Fraction] = []  # the problem's numbers the calls use (each at most as often as the problem has it)
    made_up = hits = 0
    earlier: set[Fraction] = set()  # results of earlier valid calls: a chained call may use them
    any_given = False
    for r in valid:
        numbers = [Fraction(n) for n in NUMBER.findall(r.call.arguments["expression"])]
        any_given = any_given or any(n in given for n in numbers)
        for n in numbers:
            if n in given and used.count(n) < given.count(n):
                used.append(n)
            elif n not in earlier:  # not the problem's (or used more often than it has it), not a result
                made_up += 1
        result = _value(r.content)
        hits += result is not None and result in right
        if result is not None:
            earlier.add(result)
    if not valid or not any_given:
        return {"call": 0.0, "numbers": 0.0, "value": 0.0}
    return {"call": 1.0, "numbers": len(used) / (len(given) + made_up) if given else 0.0, "value": hits / len(valid)}


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

# (case, the calculator expressions the episode's calls carry in order, answer text, finish, expected reward) for the
# word problem 1068 + 806 - 131 = 1743 (`WORD_PROBLEM`) with partial_credit 0.6: each hack earns less than the honest
# episode it imitates, and only a right answer earns 1.
WORD_PROBLEM = {"prompt": "Nora collected 1068 pencils. A friend gives her 806 more pencils. She gives away 131 pencils. "
                          "How many pencils does Nora have at the end?", "answer": "1743",
                "meta": {"ops": [["=", 1068], ["+", 806], ["-", 131]]}}
PARTIAL_AUDIT = [
    ("right call, right answer", ["1068+806-131"], "The answer is 1743.", "answer", 1.0),
    ("right call, its result ignored", ["1068+806-131"], "The answer is 1744.", "answer", 0.6),
    ("two chained calls, result ignored", ["1068+806", "1874-131"], "The answer is 1744.", "answer", 0.6),
    ("every number, a wrong sign", ["1068+806+131"], "The answer is 2005.", "answer", 0.4),
    ("a step dropped (an intermediate)", ["1068+806"], "The answer is 1874.", "answer", 0.6 * (1 + 2 / 3 + 1) / 3),
    ("hack: a call without the problem's numbers", ["1+1"], "The answer is 2.", "answer", 0.0),
    ("hack: padding with a number of its own", ["1068+806-131+5"], "The answer is 1748.", "answer", 0.6 * 1.75 / 3),
    ("hack: fishing over the numbers", ["1068+806", "1068-806", "1068*806", "806+131", "1068+131"],
     "The answer is 1199.", "answer", 0.6 * (1 + 3 / 10 + 1 / 5) / 3),
    ("hack: only refused calls", ["1068 plus 806"], "The answer is 1874.", "answer", 0.0),
    ("no call, wrong answer", [], "The answer is 1744.", "answer", 0.0),
    ("hack: a tool message copied", ["1068+806-131"], "error: unexpected ')'. The answer is 1744.", "answer", 0.0),
    ("hack: ends on a call (a limit hit)", ["1068+806-131"], "", "max_turns", 0.0),
]
