"""MathVerifier (registry name "math") and its seeded audit problems.

The whole policy is the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import math
import random
from fractions import Fraction
from typing import Any

from verifiers.base import AuditProblem, Verdict, Verifier
from verifiers.math_answer.equivalence import _Cmp, _Outcome
from verifiers.math_answer.extract import Extraction, _find_last_numbers, _last_group, extract_answer
from verifiers.math_answer.guards import DEFAULT_BUDGET, MAX_ANSWER_CHARS, Unparseable, _BudgetExceeded, _CallBudget, _sp
from verifiers.math_answer.normalize import clean_answer, parse_answer_text
from verifiers.math_answer.values import (
    Gold, Relation, Scalar, Seq, Text, _fmt_frac, _free_symbols_of, _text_key, build_value, parse_gold,
)


# --------------------------------------------------------------------------------------
# The verifier
# --------------------------------------------------------------------------------------


def _rhs(v: Any) -> Any:
    if isinstance(v, Relation) and all(op == "=" for op in v.ops):
        return v.operands[-1]
    return v


def _parse_prediction(part: str, gold: Gold) -> Any:
    cleaned = clean_answer(part, merge_thousands=not gold.sequence)
    if len(cleaned) > MAX_ANSWER_CHARS:
        raise Unparseable("answer too long")
    if isinstance(gold.value, Text):
        return Text(_text_key(part))
    value = build_value(parse_answer_text(cleaned))
    if gold.numeric and isinstance(value, (Scalar, Relation)) and _free_symbols_of(_rhs(value)):
        try:  # read stray letters as units: "5 m", "x = 5 m" (never drops list items)
            value2 = build_value(parse_answer_text(cleaned, numeric_mode=True))
            if isinstance(value2, (Scalar, Relation)) and not _free_symbols_of(_rhs(value2)):
                return value2
        except Unparseable:
            pass
    return value


class MathVerifier(Verifier):
    """Final-answer math: extraction, LaTeX normalisation, sympy equivalence (see the package docstring)."""

    name = "math"
    description = "final math answer (\\boxed, 'the answer is', ####, <answer>, last number) vs gold, by sympy equivalence"
    timeout_s = 10.0

    def __init__(self, rel_tol: float = 1e-6, allow_unevaluated: bool = False,
                 symbolic_budget: int = DEFAULT_BUDGET, timeout_s: float | None = None):
        if not (isinstance(rel_tol, (int, float)) and 0 <= rel_tol < 1):
            raise ValueError(f"math verifier: rel_tol must be in [0, 1), got {rel_tol!r}")
        if not isinstance(symbolic_budget, int) or symbolic_budget < 1000:
            raise ValueError(f"math verifier: symbolic_budget must be an int >= 1000, got {symbolic_budget!r}")
        self.rel_tol = float(rel_tol)
        self.allow_unevaluated = bool(allow_unevaluated)
        self.symbolic_budget = symbolic_budget
        if timeout_s is not None:
            self.timeout_s = float(timeout_s)

    def warmup(self) -> None:
        _sp()
        self.check("\\boxed{\\frac{1}{2}+x}", "x + 0.5")

    def _gold(self, reference: Any) -> Gold:
        if isinstance(reference, bool) or not isinstance(reference, (str, int, float, Fraction)):
            raise ValueError(f"malformed reference: expected a string or a number, got {type(reference).__name__}")
        if isinstance(reference, float):
            if not math.isfinite(reference):
                raise ValueError(f"malformed reference: {reference!r}")
            reference = repr(reference)
        elif isinstance(reference, Fraction):
            reference = f"{reference.numerator}/{reference.denominator}"
        return parse_gold(str(reference), self.symbolic_budget)

    def check(self, completion: str, reference: Any) -> Verdict:
        gold = self._gold(reference)
        if not isinstance(completion, str):
            raise TypeError(f"math verifier: completion must be a str, got {type(completion).__name__}")
        details: dict[str, Any] = {"rule": None, "extracted": None, "normalized": None, "gold": gold.show()}
        ext = extract_answer(completion)
        if ext is None:
            return Verdict(0.0, "no answer found", details)
        details["rule"] = ext.rule
        details["extracted"] = _preview(" | ".join(ext.parts))
        if ext.retracted:
            return Verdict(0.0, "answer retracted", details)
        cmp = _Cmp(self.rel_tol, self.allow_unevaluated)
        try:
            with _CallBudget(self.symbolic_budget):
                try:
                    pred = self._predict(ext, gold)
                except Unparseable as e:
                    if ext.fallback_text is None:
                        details["error"] = str(e)
                        return Verdict(0.0, "unparseable answer", details)
                    inner = _find_last_numbers(ext.fallback_text)
                    if not inner:
                        details["error"] = str(e)
                        return Verdict(0.0, "unparseable answer", details)
                    group = _last_group(inner, ext.fallback_text)
                    ext = Extraction("answer tag", [o.value for o in group])
                    details["extracted"] = _preview(" | ".join(ext.parts))
                    pred = self._predict(ext, gold)
                details["normalized"] = _preview(pred.show())
                ok = cmp.values(pred, gold.value)
        except Unparseable as e:
            details["error"] = str(e)
            return Verdict(0.0, "unparseable answer", details)
        except _Outcome as o:
            return Verdict(0.0, o.reason, details)
        except _BudgetExceeded:
            return Verdict(0.0, "comparison budget exceeded", details)
        except RecursionError:
            details["error"] = "nested too deeply"
            return Verdict(0.0, "unparseable answer", details)
        return Verdict(1.0 if ok else 0.0, "correct" if ok else "wrong answer", details)

    def _predict(self, ext: Extraction, gold: Gold) -> Any:
        values = [_parse_prediction(part, gold) for part in ext.parts]
        if len(values) == 1:
            return values[0]
        if isinstance(gold.value, Text):
            keys = {v.text for v in values}
            if len(keys) > 1:
                raise _Outcome("multiple answers")
            return values[0]
        flat: list = []
        for v in values:
            flat.extend(v.items if isinstance(v, Seq) and v.kind == "list" else [v])
        return Seq("list", flat, has_or=True)

    # -- audit support -------------------------------------------------------------
    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        return audit_problems(n, seed)

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        ref = str(problem.reference)
        gold = self._gold(problem.reference)
        d1, d2, d3 = _decoys(gold)
        cases = [
            ("boxed hedge", f"\\boxed{{{d1}}} or \\boxed{{{ref}}}", 0.0),
            ("answer-is list", f"The answer is {ref}, {d1}, {d2} or {d3}.", 0.0),
            ("retraction", f"The answer is {ref}. No wait, that's wrong, it's {d1}.", 0.0),
            ("correction honoured", f"The answer is {d1}. Wait, actually the answer is {ref}.", 1.0),
            ("boxed beats later phrase", f"\\boxed{{{d1}}}\nSome would say the answer is {ref}.", 0.0),
            ("tentative answer in think", f"<think>Maybe \\boxed{{{ref}}}?</think>\nThe answer is {d1}.", 0.0),
            ("answer tag scope", f"<think>Perhaps {d1}.</think>\n<answer>{ref}</answer>", 1.0),
            ("negated", f"The answer is not {ref}.", 0.0),
            ("power tower", "\\boxed{9^{9^{9^{9}}}}", 0.0),
            ("factorial bomb", "\\boxed{100000!}", 0.0),
            ("nested braces", "\\boxed{" + "{" * 3000 + "1" + "}" * 3000 + "}", 0.0),
            ("frac bomb", "\\boxed{" + "\\frac{1}{" * 400 + "2" + "}" * 400 + "}", 0.0),
            ("code injection", "\\boxed{__import__('os').system('echo pwned')}", 0.0),
        ]
        if isinstance(gold.value, Scalar) and gold.numeric:
            if gold.value.frac is not None and gold.value.frac != 0:
                cases.append(("plus-minus hedge", f"\\boxed{{\\pm {ref}}}", 0.0))
            if gold.value.literal and not gold.value.percent:
                cases.append(("unevaluated arithmetic", f"\\boxed{{({ref}) \\cdot 1}}", 0.0))
                cases.append(("trailing units", f"The answer is {ref} apples.", 1.0))
        return cases


def _preview(s: str, n: int = 200) -> str:
    return s if len(s) <= n else s[: n - 3] + "..."


def _decoys(gold: Gold) -> tuple[str, str, str]:
    """Three answers that are certainly wrong for this gold."""
    v = gold.value
    if isinstance(v, Scalar) and v.frac is not None:
        base = v.frac / 100 if v.percent else v.frac
        return tuple(_fmt_frac(base * 3 + k) for k in (7, 11, 13))  # type: ignore[return-value]
    if isinstance(v, Scalar) and gold.numeric:
        return ("1234567", "7654321", "1111111")
    if isinstance(v, Scalar):
        return ("0", "1234567", "7654321")
    return ("1234567", "7654321", "1111111")


# --------------------------------------------------------------------------------------
# Seeded audit problems
# --------------------------------------------------------------------------------------

_STYLES = ("boxed", "phrase", "hashes", "tag", "final", "think_boxed")


def _wrap_gold(rng: random.Random, reasoning: str, answer: str, style: str | None = None) -> str:
    style = style or rng.choice(_STYLES)
    if style == "boxed":
        return f"{reasoning} Therefore the result is $\\boxed{{{answer}}}$."
    if style == "phrase":
        return f"{reasoning}\nThe answer is {answer}."
    if style == "hashes":
        return f"{reasoning}\n#### {answer}"
    if style == "tag":
        return f"<think>{reasoning}</think>\n<answer>{answer}</answer>"
    if style == "final":
        return f"{reasoning}\n\n**Final Answer:** {answer}"
    return f"<think>{reasoning}</think>\nSo we get \\boxed{{{answer}}}"


def _gen_integer(rng):
    a, b, c = rng.randint(2, 99), rng.randint(2, 30), rng.randint(2, 30)
    val = a + b * c
    return (f"Compute {a} plus the product of {b} and {c}.", str(val),
            f"First {b} times {c} is {b * c}, then add {a}.", str(val))


def _gen_negative(rng):
    a, b = rng.randint(1, 50), rng.randint(60, 120)
    return (f"Subtract {b} from {a}.", str(a - b), f"We take {a} minus {b}.", rng.choice([str(a - b), f"\u2212{b - a}"]))


def _gen_fraction(rng):
    b, d = rng.choice([2, 3, 4, 5, 6, 8]), rng.choice([3, 5, 7, 9])
    a, c = rng.randint(1, b - 1), rng.randint(1, d - 1)
    f = Fraction(a, b) + Fraction(c, d)
    ref = rng.choice([f"\\frac{{{f.numerator}}}{{{f.denominator}}}", f"{f.numerator}/{f.denominator}"])
    ans = rng.choice([f"\\dfrac{{{f.numerator}}}{{{f.denominator}}}", f"{f.numerator}/{f.denominator}",
                      f"\\frac{{{f.numerator * 2}}}{{{f.denominator * 2}}}"])
    return (f"Add the fractions a/{b} with a = {a} and c/{d} with c = {c}.", ref,
            f"Common denominator {b * d // math.gcd(b, d)}.", ans)


def _gen_decimal(rng):
    a = Fraction(rng.randint(11, 99), 10)
    b = Fraction(rng.randint(2, 9), 2)
    v = a * b
    ref = f"{float(v):.2f}".rstrip("0").rstrip(".")
    ans = rng.choice([ref, f"{float(v):.3f}", f"\\frac{{{v.numerator}}}{{{v.denominator}}}"])
    return (f"Multiply {float(a)} by one half of {int(b * 2)}.", ref, f"Half of {int(b * 2)} is {float(b)}.", ans)


def _gen_thousands(rng):
    a, b = rng.randint(1000, 9999), rng.randint(100, 999)
    v = a * b
    return (f"A factory makes {a} parts per day. How many parts does it make in {b} days?", str(v),
            f"Multiply {a} by {b}.", rng.choice([f"{v:,}", f"{v:,} parts", str(v)]))


def _gen_percent(rng):
    whole = rng.choice([20, 40, 50, 80, 200, 400])
    pct = rng.choice([5, 10, 25, 75])
    part = whole * pct // 100
    return (f"{part} of the {whole} students wear glasses. What percent wear glasses?", f"{pct}\\%",
            f"Divide {part} by {whole}.", rng.choice([f"{pct}\\%", f"{pct}%", f"{pct} percent"]))


def _gen_sqrt(rng):
    k, m = rng.randint(2, 9), rng.choice([2, 3, 5, 6, 7])
    n = k * k * m
    return (f"Simplify the square root of {n}.", f"{k}\\sqrt{{{m}}}", f"Factor {n} = {k * k} * {m}.",
            rng.choice([f"{k}\\sqrt{{{m}}}", f"{k} \\sqrt {m}", f"\\sqrt{{{m}}} \\cdot {k}"]))


def _gen_pi(rng):
    r = rng.randint(2, 12)
    return (f"What is the area of a circle of radius {r}?", f"{r * r}\\pi", f"Area is pi r^2 with r = {r}.",
            rng.choice([f"{r * r}\\pi", f"\\pi \\cdot {r * r}", f"{r * r}\u03c0"]))


def _gen_set(rng):
    r1, r2 = rng.sample(range(-9, 10), 2)
    s, p = -(r1 + r2), r1 * r2
    poly = f"x^2 {'+' if s >= 0 else '-'} {abs(s)}x {'+' if p >= 0 else '-'} {abs(p)}"
    lo, hi = sorted((r1, r2))
    ref = rng.choice([f"\\{{{lo}, {hi}\\}}", f"{lo}, {hi}"])
    ans = rng.choice([f"{hi}, {lo}", f"\\{{{hi}, {lo}\\}}", f"x = {lo} \\text{{ or }} x = {hi}"])
    return (f"Find all roots of {poly} = 0.", ref, "Factor the quadratic.", ans)


def _gen_interval(rng):
    a, b = rng.randint(2, 6), rng.randint(1, 20)
    c = b + a * rng.randint(1, 9)
    k = (c - b) // a
    strict = rng.random() < 0.5
    ref = f"({k}, \\infty)" if strict else f"[{k}, \\infty)"
    relation = ">" if strict else "\\ge"
    ans = rng.choice([ref, f"x {relation} {k}"])
    sign = ">" if strict else ">="
    return (f"Solve {a}x + {b} {sign} {c} for real x.", ref, f"Subtract {b} and divide by {a}.", ans)


def _gen_tuple(rng):
    x, y = rng.randint(-9, 9), rng.randint(-9, 9)
    return (f"Find the point where the lines x = {x} and y = {y} meet, as (x, y).", f"({x}, {y})",
            "Read off both coordinates.", f"\\left( {x}, {y} \\right)")


def _gen_symbolic(rng):
    a, b = rng.randint(1, 9), rng.randint(1, 9)
    ref = f"x^2 + {a + b}x + {a * b}"
    ans = rng.choice([f"x^{{2}}+{a + b}x+{a * b}", f"(x+{a})(x+{b})", f"{a * b} + {a + b} x + x^2"])
    return (f"Expand (x + a)(x + b) with a = {a} and b = {b}.", ref, "Use FOIL.", ans)


def _gen_equation(rng):
    a, x = rng.randint(2, 9), rng.randint(-9, 9)
    b = rng.randint(1, 20)
    c = a * x + b
    ref = rng.choice([str(x), f"x = {x}"])
    return (f"Solve {a}x + {b} = {c} for x.", ref, f"Subtract {b} and divide by {a}.",
            rng.choice([f"x = {x}", str(x)]))


def _gen_scientific(rng):
    m, e = rng.randint(11, 99), rng.randint(4, 8)
    v = m * 10 ** (e - 1)
    ref = f"{m / 10} \\times 10^{{{e}}}"
    ans = rng.choice([str(v), f"{m / 10}e{e}", f"{m / 10} \\cdot 10^{e}"])
    return (f"Write {m} times ten to the power {e - 1} in scientific notation.", ref, "Move the decimal point.", ans)


def _gen_choice(rng):
    letters = "ABCDE"
    correct = rng.choice(letters)
    return ("Which option is correct? (A) one (B) two (C) three (D) four (E) five", correct,
            "Check each option in turn.", f"({correct})")


_GENERATORS = (_gen_integer, _gen_negative, _gen_fraction, _gen_decimal, _gen_thousands, _gen_percent,
               _gen_sqrt, _gen_pi, _gen_set, _gen_interval, _gen_tuple, _gen_symbolic, _gen_equation,
               _gen_scientific, _gen_choice)


def audit_problems(n: int, seed: int = 0) -> list[AuditProblem]:
    """n seeded problems cycling through 15 answer kinds, each with a gold completion."""
    rng = random.Random(seed)
    checker = MathVerifier()
    out: list[AuditProblem] = []
    seen: set = set()
    for k in range(n):
        gen = _GENERATORS[k % len(_GENERATORS)]
        for _attempt in range(50):
            prompt, ref, reasoning, ans = gen(rng)
            keys = _answer_keys(parse_gold(ref))
            # answers must differ across problems (the audit uses other problems' golds as wrong
            # answers) and the prompt alone must not state the answer
            if keys & seen or checker.check(prompt, ref).score > 0:
                continue
            break
        seen |= keys
        out.append(AuditProblem(prompt=prompt, reference=ref, gold=_wrap_gold(rng, reasoning, ans)))
    return out


def _answer_keys(gold: Gold) -> set:
    v = gold.value
    if isinstance(v, Scalar) and v.frac is not None:
        return {v.frac, v.frac / 100} if v.percent else {v.frac}
    if isinstance(v, Relation) and isinstance(v.operands[-1], Scalar) and v.operands[-1].frac is not None:
        return {v.operands[-1].frac}
    return {gold.show()}
