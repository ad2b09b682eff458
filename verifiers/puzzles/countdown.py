"""Countdown: reach a target with + - * / and parentheses over given numbers, each used at most once.

Reference: ``{"family": "countdown", "numbers": [int, ...], "target": int}``.

Answer: one arithmetic expression, read from the answer scope (see `common`): the whole
``<answer>`` / ``\\boxed{}`` content, or in free text the last expression-looking run on the
last line that has one ("So: (3 + 5) * 2 = 16." works). A chain of equalities is fine when
every part has the same value ("(3+5)*2 = 16", "16 = (3+5)*2", "(3+5)*2 = 8*2 = 16"); the
first part that is not a bare number is the answer and must use the given numbers.
Unicode and LaTeX operators (×, ÷, −, \\times, \\cdot, \\div, \\frac{a}{b}) and "3 x 4" are
read as arithmetic.

Parsing is `ast.parse(mode="eval")`, never eval: only non-negative integer literals, binary
+ - * / and parentheses are allowed (no unary minus: it would manufacture numbers).
Arithmetic is exact (`Fraction`); a division by zero scores 0 with its own reason.

Generator: picks the numbers, builds a random expression over most of them with exact
arithmetic and positive intermediate values, and takes its value as the target; the
expression is the gold. Difficulty d (1-5) gives d + 2 numbers. Split: "train" numbers lie
in 1..50; "test" problems always include at least one number in 51..100, so the two never
share a problem. Within one batch, no problem's gold also solves another problem.
"""
from __future__ import annotations

import ast
import random
import re
from collections import Counter
from fractions import Fraction
from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict
from posttrain.verifiers.puzzles.common import (PuzzleVerifier, Split, check_generate_args, generate_unique, make_rng,
                                      require, strip_markup)

FAMILY = "countdown"
DIFFICULTIES = range(1, 6)
MAX_EXPRESSION_CHARS = 500
_OPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/"}
_EXPR_RUN = re.compile(r"[0-9][0-9+\-*/().= ]*[0-9)]|\([0-9+\-*/().= ]*[0-9)]")


class _Rejected(Exception):
    """An answer that breaks the rules; the message is the verdict reason."""


# ---------------------------------------------------------------------- expressions
def _normalize(text: str) -> str:
    text = strip_markup(text, keep_stars=True)
    for a, b in (("\\left", ""), ("\\right", ""), ("\\times", "*"), ("\\cdot", "*"), ("\\div", "/"),
                 ("\\,", ""), ("\\!", ""), ("$", ""), ("\\(", ""), ("\\)", ""), ("\\[", ""), ("\\]", ""),
                 ("×", "*"), ("·", "*"), ("∙", "*"), ("÷", "/"), ("−", "-"), ("–", "-"), ("⁄", "/")):
        text = text.replace(a, b)
    previous = None
    while previous != text:  # innermost \frac{a}{b} first
        previous = text
        text = re.sub(r"\\[dt]?frac\{([^{}]*)\}\{([^{}]*)\}", r"((\1)/(\2))", text)
    text = text.replace("{", "(").replace("}", ")")
    return re.sub(r"(?<=[\d)])\s*[xX]\s*(?=[\d(])", " * ", text)


def _check_tree(node: ast.AST) -> None:
    if isinstance(node, ast.Expression):
        return _check_tree(node.body)
    if isinstance(node, ast.BinOp):
        if type(node.op) not in _OPS:
            symbol = {ast.Pow: "**", ast.FloorDiv: "//", ast.Mod: "%"}.get(type(node.op), type(node.op).__name__)
            raise _Rejected(f"operator {symbol} not allowed")
        _check_tree(node.left)
        _check_tree(node.right)
        return None
    if isinstance(node, ast.Constant):
        if type(node.value) is not int:
            raise _Rejected(f"literal {node.value!r} not allowed (integers only)")
        return None
    if isinstance(node, ast.UnaryOp):
        raise _Rejected("unary operator not allowed")
    what = {ast.Call: "function call", ast.Attribute: "attribute access", ast.Name: "name",
            ast.Subscript: "subscript", ast.Compare: "comparison", ast.BoolOp: "boolean operator"}
    raise _Rejected(f"{what.get(type(node), type(node).__name__)} not allowed")


def _parse(text: str) -> ast.Expression:
    if len(text) > MAX_EXPRESSION_CHARS:
        raise _Rejected("expression too long")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        raise _Rejected("unparseable expression") from None
    _check_tree(tree)
    return tree


def _literals(node: ast.AST) -> list[int]:
    return [n.value for n in ast.walk(node) if isinstance(n, ast.Constant)]


def _evaluate(node: ast.AST) -> Fraction:
    if isinstance(node, ast.Expression):
        return _evaluate(node.body)
    if isinstance(node, ast.Constant):
        return Fraction(node.value)
    assert isinstance(node, ast.BinOp)
    a, b = _evaluate(node.left), _evaluate(node.right)
    op = type(node.op)
    if op is ast.Add:
        return a + b
    if op is ast.Sub:
        return a - b
    if op is ast.Mult:
        return a * b
    if b == 0:
        raise _Rejected("division by zero")
    return a / b


def _fmt(x: Fraction) -> str:
    return str(x.numerator) if x.denominator == 1 else f"{x.numerator}/{x.denominator}"


def _find_in_text(text: str) -> str | None:
    """The last expression-looking run (with an operator) on the last line that has one."""
    for line in reversed(text.splitlines()):
        line = _normalize(line)
        if ":" in line:
            line = line.rsplit(":", 1)[1]
        runs = [r for r in _EXPR_RUN.findall(line) if re.search(r"\d\s*[-+*/]\s*[\d(]|\)\s*[-+*/]", r)]
        if runs:
            return runs[-1].strip().rstrip(".= ")
    return None


def score_expression(answer: str, numbers: list[int], target: int) -> tuple[float, str, dict[str, Any]]:
    """(score, reason, details) for one answer string (already scoped)."""
    parts = [p for p in (p.strip() for p in answer.split("=")) if p]
    details: dict[str, Any] = {"expression": answer[:200]}
    try:
        if not parts:
            raise _Rejected("no answer found")
        trees = [_parse(p) for p in parts]
        main = next((t for t in trees if not isinstance(t.body, ast.Constant)), None)
        if main is None:
            raise _Rejected("a bare number is not an expression")
        used = Counter(_literals(main))
        details["numbers_used"] = sorted(used.elements())
        given = Counter(numbers)
        for value, count in sorted(used.items()):
            if value not in given:
                raise _Rejected(f"uses {value}, which is not among the numbers")
            if count > given[value]:
                raise _Rejected(f"uses {value} {count} times but it is given {given[value]} time(s)")
        value = _evaluate(main)
        details["value"] = _fmt(value)
        for t in trees:  # every part of a chain of equalities must agree
            if t is not main and _evaluate(t) != value:
                raise _Rejected(f"claims {_fmt(_evaluate(t))} but the expression equals {_fmt(value)}")
        if value != target:
            raise _Rejected(f"evaluates to {_fmt(value)}, not {target}")
    except _Rejected as exc:
        return 0.0, str(exc), details
    return 1.0, "correct", details


# ---------------------------------------------------------------------- generator
def _draw_numbers(rng: random.Random, count: int, split: Split) -> list[int]:
    def one(hi: int) -> int:
        return rng.randint(1, 10) if rng.random() < 0.6 else rng.randint(11, hi)

    if split == "train":
        return [one(50) for _ in range(count)]
    numbers = [rng.randint(51, 100)] + [one(100) for _ in range(count - 1)]
    rng.shuffle(numbers)
    return numbers


def _random_expression(rng: random.Random, values: list[int]) -> tuple[Fraction, str] | None:
    items = [(Fraction(v), str(v), 3) for v in values]  # (value, text, precedence)
    while len(items) > 1:
        i, j = rng.sample(range(len(items)), 2)
        (a, ta, pa), (b, tb, pb) = items[i], items[j]
        choices = ["+"]
        if a != b:
            choices.append("-")
        if a != 1 and b != 1:
            choices += ["*", "*"]
        if b not in (0, 1) and (a / b).denominator == 1:
            choices += ["/", "/"]
        op = rng.choice(choices)
        if op == "-" and a < b:
            (a, ta, pa), (b, tb, pb) = (b, tb, pb), (a, ta, pa)
        if op == "+":
            node = (a + b, f"{ta} + {tb}", 1)
        elif op == "-":
            node = (a - b, f"{ta} - {tb if pb > 1 else f'({tb})'}", 1)
        elif op == "*":
            node = (a * b, f"{ta if pa > 1 else f'({ta})'} * {tb if pb > 1 else f'({tb})'}", 2)
        else:
            node = (a / b, f"{ta if pa > 1 else f'({ta})'} / {tb if pb > 2 else f'({tb})'}", 2)
        items = [x for k, x in enumerate(items) if k not in (i, j)] + [node]
    value, text, _ = items[0]
    return (value, text) if value.denominator == 1 else None


def generate(n: int, seed: int = 0, split: Split = "train", difficulty: int = 2) -> list[dict[str, Any]]:
    """`n` distinct solvable problems: [{"prompt", "reference", "gold"}, ...], deterministic per arguments."""
    check_generate_args(n, split, difficulty, DIFFICULTIES)
    rng = make_rng(FAMILY, seed, split, difficulty)
    count = difficulty + 2
    max_target = 100 * 10 ** min(difficulty, 2)

    def make(r: random.Random) -> dict[str, Any] | None:
        numbers = _draw_numbers(r, count, split)
        used = r.sample(numbers, r.randint(max(2, count - 1), count))
        built = _random_expression(r, used)
        if built is None:
            return None
        value, gold = built
        target = int(value)
        if not 10 <= target <= max_target or target in numbers:
            return None
        reference = {"family": FAMILY, "numbers": numbers, "target": target, "split": split, "difficulty": difficulty}
        return {"prompt": _prompt(numbers, target), "reference": reference, "gold": f"<answer>{gold}</answer>",
                "_uses": Counter(used)}

    by_target: dict[int, list[dict[str, Any]]] = {}

    def compatible(item: dict[str, Any]) -> bool:
        ref = item["reference"]
        for other in by_target.get(ref["target"], []):  # neither gold may solve the other problem
            if not (item["_uses"] - Counter(other["reference"]["numbers"])) or \
                    not (other["_uses"] - Counter(ref["numbers"])):
                return False
        by_target.setdefault(ref["target"], []).append(item)
        return True

    items = generate_unique(n, rng, make, lambda x: (tuple(sorted(x["reference"]["numbers"])), x["reference"]["target"]),
                            "countdown.generate", compatible=compatible)
    for item in items:
        del item["_uses"]
    return items


def _prompt(numbers: list[int], target: int) -> str:
    listed = ", ".join(map(str, numbers))
    return (f"Using the numbers {listed}, write an arithmetic expression that equals {target}. "
            "You may use +, -, *, / and parentheses. Each number may be used at most once, and you do not "
            "have to use all of them. Put only the expression inside <answer></answer> tags.")


# ---------------------------------------------------------------------- verifier
class CountdownVerifier(PuzzleVerifier):
    """Countdown arithmetic puzzles (module docstring): 1.0 when the expression is legal and hits the target."""

    name = "countdown"
    description = "Countdown: an expression over the given numbers (each at most once) that equals the target"
    family = FAMILY
    default_difficulty = 2
    generate = staticmethod(generate)

    def parse_reference(self, reference: Any) -> tuple[list[int], int]:
        require(isinstance(reference, dict), "countdown reference must be a dict with 'numbers' and 'target'")
        numbers, target = reference.get("numbers"), reference.get("target")
        require(isinstance(numbers, list) and bool(numbers) and all(type(x) is int and x >= 0 for x in numbers),
                f"countdown reference 'numbers' must be a non-empty list of non-negative ints, got {numbers!r}")
        require(type(target) is int, f"countdown reference 'target' must be an int, got {target!r}")
        return numbers, target

    def check_scope(self, scope: str, rule: str, ref: tuple[list[int], int]) -> Verdict:
        numbers, target = ref
        if rule == "text":
            answer = _find_in_text(scope)
            if answer is None:
                return Verdict(0.0, "no answer found", {"rule": rule})
        else:
            answer = _normalize(scope)
            if ":" in answer:  # "Expression: (3 + 5) * 2"
                answer = answer.rsplit(":", 1)[1]
            answer = answer.strip().rstrip(".").strip("*").strip()  # markdown bold around the answer
        score, reason, details = score_expression(answer, numbers, target)
        return Verdict(score, reason, {"rule": rule, **details})

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        numbers, target = self.parse_reference(problem.reference)
        gold = problem.gold.split("<answer>")[-1].split("</answer>")[0]
        tree = _parse(gold)
        used = Counter(_literals(tree))
        x = next(iter(used))
        missing = next(v for v in range(1, 1000) if v not in numbers)
        wrong = next(f"{a} {op} {b}" for a in numbers for b in numbers for op in "+*-"
                     if a is not b and Fraction(eval_safe(f"{a} {op} {b}")) != target)
        overuse = f"({gold})" + f" + {x} - {x}" * Counter(numbers)[x]
        return [
            ("number used too often", f"<answer>{overuse}</answer>", 0.0),
            ("number not given", f"<answer>({gold}) * {missing} / {missing}</answer>", 0.0),
            ("function call", f"<answer>abs({gold})</answer>", 0.0),
            ("import call", f"<answer>__import__('os').getpid() * 0 + {target}</answer>", 0.0),
            ("attribute access", f"<answer>({gold}).real</answer>", 0.0),
            ("huge power", "<answer>9**9**9</answer>", 0.0),
            ("bare target", f"<answer>{target}</answer>", 0.0),
            ("unary minus", f"<answer>-(-({gold}))</answer>", 0.0),
            ("float literal", f"<answer>({gold}) * 1.0</answer>", 0.0),
            ("wrong value claimed correct", f"<answer>{wrong} = {target}</answer>", 0.0),
            ("division by zero", f"<answer>{x} / ({x} - {x})</answer>", 0.0),
            ("name", "<answer>target</answer>", 0.0),
            ("deep nesting", "<answer>" + "(" * 300 + "1" + ")" * 300 + "</answer>", 0.0),
        ]


def eval_safe(expression: str) -> Fraction:
    """Exact value of an expression under the Countdown grammar (raises ValueError if illegal)."""
    try:
        return _evaluate(_parse(expression))
    except _Rejected as exc:
        raise ValueError(str(exc)) from None
