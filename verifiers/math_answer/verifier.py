"""MathVerifier (registry name "math") and its seeded audit problems.

The whole policy is the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import math
import random
import re
from fractions import Fraction
from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier
from posttrain.verifiers.math_answer.equivalence import _Cmp, _Outcome
from posttrain.verifiers.math_answer.extract import Extraction, _find_last_numbers, _last_group, extract_answer
from posttrain.verifiers.math_answer.guards import DEFAULT_BUDGET, MAX_ANSWER_CHARS, Unparseable, _BudgetExceeded, _CallBudget, _sp
from posttrain.verifiers.math_answer.normalize import clean_answer, parse_answer_text
from posttrain.verifiers.math_answer.values import (
    Gold, Matrix, Relation, Scalar, Seq, Text, _fmt_frac, _free_symbols_of, _safe_str, _text_key, build_value,
    parse_gold,
)


# --------------------------------------------------------------------------------------
# The verifier
# --------------------------------------------------------------------------------------


def _rhs(v: Any) -> Any:
    if isinstance(v, Relation) and all(op == "=" for op in v.ops):
        return v.operands[-1]
    return v


_SPACED_NUMBERS_RE = re.compile(r"-?\d+(?: -?\d+)+")


def _parse_prediction(part: str, gold: Gold) -> Any:
    cleaned = clean_answer(part, merge_thousands=not gold.sequence)
    if len(cleaned) > MAX_ANSWER_CHARS:
        raise Unparseable("answer too long")
    if isinstance(gold.value, Text):
        return Text(_text_key(part))
    if gold.sequence and _SPACED_NUMBERS_RE.fullmatch(cleaned):
        cleaned = cleaned.replace(" ", ", ")  # "100 200 300" for a list gold: three numbers, not thousands
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

    def __init__(self, rel_tol: float = 1e-6, require_simplified: bool = False,
                 symbolic_budget: int = DEFAULT_BUDGET, timeout_s: float | None = None,
                 allow_unevaluated: bool | None = None):
        if not (isinstance(rel_tol, (int, float)) and 0 <= rel_tol < 1):
            raise ValueError(f"math verifier: rel_tol must be in [0, 1), got {rel_tol!r}")
        if not isinstance(symbolic_budget, int) or symbolic_budget < 1000:
            raise ValueError(f"math verifier: symbolic_budget must be an int >= 1000, got {symbolic_budget!r}")
        if allow_unevaluated is not None:  # the old name of the same switch, inverted
            if require_simplified and allow_unevaluated:
                raise ValueError("math verifier: require_simplified=True contradicts allow_unevaluated=True")
            require_simplified = not allow_unevaluated
        self.rel_tol = float(rel_tol)
        self.require_simplified = bool(require_simplified)
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
        cmp = _Cmp(self.rel_tol, self.require_simplified)
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
        return audit_problems(n, seed, require_simplified=self.require_simplified)

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
        strict = 0.0 if self.require_simplified else 1.0
        v = gold.value
        if isinstance(v, Scalar) and gold.numeric:
            if v.frac is not None and v.frac != 0:
                cases.append(("plus-minus hedge", f"\\boxed{{\\pm {ref}}}", 0.0))
            if v.literal and not v.percent:
                # a closed form of the gold: accepted, unless the verifier requires simplified answers
                cases.append(("unevaluated arithmetic", f"\\boxed{{({ref}) \\cdot 1}}", strict))
                cases.append(("trailing units", f"The answer is {ref} apples.", 1.0))
            # a retraction followed by the answer, and the other way round
            cases.append(("retraction then answer", f"The answer is {d1}. No, it isn't {d1}; it's {ref}.", 1.0))
            cases.append(("answer then retraction", f"The answer is {ref}. Hmm, it isn't {ref}; it's {d1}.", 0.0))
            cases.append(("negated alternative", f"After checking, it's {ref}, not {d1}.", 1.0))
            cases.append(("negated answer phrase", f"The answer isn't {ref}; it's {d1}.", 0.0))
            if v.frac is not None and not v.percent:
                cases.extend(_number_cases(v.frac, strict))
        elif isinstance(v, Scalar):
            cases.extend(_symbolic_cases(ref, v))
        elif isinstance(v, Matrix):
            cases.extend(_matrix_cases(v))
        return cases


def _number_cases(value: Fraction, strict: float) -> list[tuple[str, str, float]]:
    """Factorials, number words, spaced thousands and repeating decimals for a rational gold."""
    cases = []
    if value.denominator == 1:
        n = value.numerator
        if n >= 3:  # n! is not n: the trailing "!" is a factorial, in a box and after a digit in prose
            cases.append(("factorial of the answer", f"\\boxed{{{n}!}}", 0.0))
            cases.append(("factorial in prose", f"So the answer is {n}!", 0.0))
        for m in range(3, 12):
            if math.factorial(m) == n:
                cases.append(("factorial form", f"\\boxed{{{m}!}}", strict))
        if abs(n) < 10 ** 9:
            cases.append(("number words", f"The answer is {number_words(n)}.", 1.0))
            cases.append(("wrong number words", f"The answer is {number_words(n + 1 + abs(n) // 50)}.", 0.0))
        if n >= 1000:
            cases.append(("space thousands in prose", f"All told, the count comes to {n:,}.".replace(",", " "), 1.0))
    elif _repeating(value) is not None:
        cases.append(("repeating decimal", f"\\boxed{{{_repeating(value)}}}", 1.0))
        cases.append(("truncated decimal", f"\\boxed{{{float(value):.2f}}}", 0.0))
    return cases


def _symbolic_cases(ref: str, v: Scalar) -> list[tuple[str, str, float]]:
    """Identities that hold only for some signs of the variables must be refuted."""
    sp = _sp()
    expr = v.expr()
    if expr.has(sp.Abs):
        dropped = expr.replace(sp.Abs, lambda u: u)
        return [("absolute value dropped", f"\\boxed{{{_safe_str(dropped).replace('**', '^')}}}", 0.0)]
    if _changes_sign(expr):  # |g| and sqrt(g^2) differ from g where g < 0
        return [("sign-blind identity", f"\\boxed{{\\sqrt{{({ref})^2}}}}", 0.0),
                ("absolute value added", f"\\boxed{{\\left|{ref}\\right|}}", 0.0)]
    return []


def _changes_sign(expr) -> bool:
    """A one-variable polynomial with a real root of odd multiplicity (it is negative somewhere)."""
    sp = _sp()
    if len(expr.free_symbols) != 1 or not expr.is_polynomial():
        return False
    x = next(iter(expr.free_symbols))
    _, factors = sp.factor_list(expr, x)
    return any(mult % 2 == 1 and sp.Poly(f, x).count_roots() > 0 for f, mult in factors)


def _matrix_cases(v: Matrix) -> list[tuple[str, str, float]]:
    rows = [[x.show() for x in row] for row in v.rows]
    cases = []
    changed = [list(r) for r in rows]
    changed[0][0] = f"{changed[0][0]} + 1"
    cases.append(("matrix entry changed", "\\boxed{" + _pmatrix(changed) + "}", 0.0))
    r, c = v.shape
    flat = [x for row in rows for x in row]
    if r == 1 or c == 1:
        cases.append(("vector as a tuple", f"\\boxed{{({', '.join(flat)})}}", 1.0))
        cases.append(("vector transposed", "\\boxed{" + _pmatrix([list(t) for t in zip(*rows)]) + "}", 0.0))
    else:
        cases.append(("matrix flattened", f"\\boxed{{({', '.join(flat)})}}", 0.0))
        if [list(t) for t in zip(*rows)] != rows:
            cases.append(("matrix transposed", "\\boxed{" + _pmatrix([list(t) for t in zip(*rows)]) + "}", 0.0))
    return cases


def _pmatrix(rows: list[list[str]]) -> str:
    return "\\begin{pmatrix} " + " \\\\ ".join(" & ".join(r) for r in rows) + " \\end{pmatrix}"


_ONES = ("zero one two three four five six seven eight nine ten eleven twelve thirteen fourteen fifteen sixteen "
         "seventeen eighteen nineteen").split()
_TENS_WORDS = "_ _ twenty thirty forty fifty sixty seventy eighty ninety".split()


def number_words(n: int, and_: bool = False) -> str:
    """English words for an integer (|n| < 10**9): 42 -> "forty-two", 105 -> "one hundred five"."""
    if n < 0:
        return "minus " + number_words(-n, and_)
    if n < 20:
        return _ONES[n]
    if n < 100:
        return _TENS_WORDS[n // 10] + ("-" + _ONES[n % 10] if n % 10 else "")
    if n < 1000:
        rest = n % 100
        return _ONES[n // 100] + " hundred" + ((" and " if and_ else " ") + number_words(rest) if rest else "")
    for scale, word in ((10 ** 6, "million"), (1000, "thousand")):
        if n >= scale:
            rest = n % scale
            return number_words(n // scale) + f" {word}" + (" " + number_words(rest, and_) if rest else "")
    raise ValueError(n)


def _repeating(value: Fraction) -> str | None:
    """0.1\\overline{6} for 1/6; None when the decimal terminates or the period is long."""
    if value < 0:
        inner = _repeating(-value)
        return None if inner is None else "-" + inner
    whole, rem, q = value.numerator // value.denominator, value.numerator % value.denominator, value.denominator
    digits, seen = [], {}
    while rem and rem not in seen and len(digits) < 12:
        seen[rem] = len(digits)
        rem *= 10
        digits.append(str(rem // q))
        rem %= q
    if not rem or rem not in seen:
        return None
    k = seen[rem]
    return f"{whole}." + "".join(digits[:k]) + "\\overline{" + "".join(digits[k:]) + "}"


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
    if style == "raw":  # the generator wrote the whole completion
        return answer
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


def _gen_factorial(rng, strict=False):
    k = rng.randint(4, 9)
    v = math.factorial(k)
    forms = [str(v)] if strict else [f"{k}!", str(v), f"{k}! = {v}", f"{k}!"]
    style = None if strict else rng.choice([None, "phrase"])  # "The answer is 5!.": after a digit, a factorial
    return (f"In how many different orders can {k} different books stand on a shelf?", str(v),
            f"Any of the {k} books can go first, and so on.", rng.choice(forms), style)


def _gen_abs(rng, strict=False):
    a = rng.randint(1, 9)
    return (f"Simplify the square root of the square of (x minus {a}), for real x.", f"|x - {a}|",
            "A square root is never negative.",
            rng.choice([f"|x-{a}|", f"\\sqrt{{(x-{a})^2}}", f"|{a} - x|", f"\\left| x - {a} \\right|"]))


def _gen_identity(rng, strict=False):
    k = rng.randint(2, 40)
    pair = rng.choice([("cosh", "sinh", "minus", "-", "u"), ("sin", "cos", "plus", "+", "t")])
    f, g, word, op, var = pair
    forms = [str(k + 1)] if strict else [str(k + 1), f"\\{f}^2 {var} {op} \\{g}^2 {var} + {k}"]
    return (f"What is {f} squared of {var} {word} {g} squared of {var}, plus {k}, for every real {var}?", str(k + 1),
            "Use the Pythagorean identity.", rng.choice(forms))


def _gen_negative_denominator(rng, strict=False):
    b = rng.choice([3, 4, 5, 7, 8, 9, 11])
    a = rng.choice([x for x in range(1, 3 * b) if math.gcd(x, b) == 1 and x % b])
    return (f"Divide {a} by the negative of {b}; give the result as a fraction.", f"-{a}/{b}",
            f"A positive divided by a negative is negative.",
            rng.choice([f"\\frac{{{a}}}{{-{b}}}", f"-\\frac{{{a}}}{{{b}}}", f"\\frac{{-{a}}}{{{b}}}", f"{a}/(-{b})"]))


def _gen_closed_form(rng, strict=False):
    kind = rng.choice(["binom", "log", "root", "sum"])
    if kind == "binom":
        n = rng.randint(6, 12)
        k = rng.randint(2, n - 2)
        v = math.comb(n, k)
        prompt, forms = f"How many ways are there to choose {k} of {n} people?", [f"\\binom{{{n}}}{{{k}}}", f"{{{n} \\choose {k}}}"]
    elif kind == "log":
        b, e = rng.randint(2, 5), rng.randint(2, 6)
        v = e
        prompt, forms = f"To what power must {b} be raised to give {b ** e}?", [f"\\log_{{{b}}} {b ** e}", f"\\log_{b}{{{b ** e}}}"]
    elif kind == "root":
        b, e = rng.randint(2, 7), rng.randint(3, 5)
        v = b
        prompt, forms = f"Which positive number has {b ** e} as its power of order {e}?", [f"\\sqrt[{e}]{{{b ** e}}}"]
    else:
        p, q = rng.randint(10, 60), rng.randint(10, 60)
        v = p + q
        prompt, forms = f"Find y when y minus {p} equals {q}.", [f"y = {p} + {q}", f"{q} + {p}"]
    return prompt, str(v), "Evaluate it.", str(v) if strict else rng.choice(forms + [str(v)])


def _gen_number_words(rng, strict=False):
    w, d = rng.randint(2, 300), rng.randint(1, 6)
    v = 7 * w + d
    return (f"How many days are there in {w} weeks and {d} days?", str(v), f"Each week has 7 days.",
            number_words(v, and_=rng.random() < 0.5))


def _gen_repeating(rng, strict=False):
    q = rng.choice([3, 6, 7, 9, 11, 12, 13, 15, 22, 27, 33, 37])
    p = rng.choice([x for x in range(1, 3 * q) if math.gcd(x, q) == 1 and x % q])
    rep = _repeating(Fraction(p, q))
    forms = [rep]
    if "\\overline{" in rep and len(rep.split("\\overline{")[1]) == 2:  # one digit repeats: also 0.\dot{3}, 0.(3)
        head, digit = rep.split("\\overline{")[0], rep.split("\\overline{")[1][0]
        forms += [f"{head}\\dot{{{digit}}}", f"{head}({digit})", f"{head}{digit * 4}\\ldots"]
    return (f"A recipe uses {p} cups of flour for {q} cakes. How many cups go into one cake, as a decimal?",
            f"\\frac{{{p}}}{{{q}}}", f"Divide {p} by {q}; the digits repeat.", rng.choice(forms))


def _gen_spaced_thousands(rng, strict=False):
    a, b = rng.randint(120, 990), rng.randint(30, 99)
    v = a * b
    spaced = f"{v:,}".replace(",", rng.choice([" ", "\u00a0", "\u202f"]))
    gold = (f"A printer prints {a} pages an hour for {b} hours; we multiply {a} by {b}. "
            f"So the printer makes {spaced} pages in total.")
    return (f"A printer prints {a} pages an hour. How many pages does it print in {b} hours?", str(v),
            "", gold, "raw")


def _gen_retraction(rng, strict=False):
    a, b = rng.randint(3, 40), rng.randint(3, 40)
    wrong = a * b + rng.choice([-1, 1]) * rng.randint(1, 5)
    gold = (f"<think>{a} times {b}...</think>\nThe answer is {wrong}. No, it isn't {wrong}; "
            f"it's {a * b}." if rng.random() < 0.5 else
            f"I first got {wrong}. The answer isn't {wrong}; it's {a * b}.")
    return (f"A hall has {a} rows of {b} seats. How many seats are there?", str(a * b), "", gold, "raw")


def _gen_plain_expression(rng, strict=False):
    k = rng.randint(2, 9)
    var = rng.choice("abyt")
    if rng.random() < 0.5:
        ref, prompt = f"({var}-{k})^2", f"Factor the square of {var}, minus {2 * k} times {var}, plus {k * k}."
        ans = rng.choice([f"({var}-{k})^2", f"({var} - {k})^2", f"({var}-{k})({var}-{k})"])
    else:
        ref, prompt = f"({var}-{k})({var}+{k})", f"Factor the square of {var} minus {k * k}."
        ans = rng.choice([f"({var}-{k})({var}+{k})", f"({var} + {k})({var} - {k})"])
    gold = f"We look for two factors. So the expression factors as {ans}."
    return prompt, ref, "", gold, "raw"


def _gen_matrix(rng, strict=False):
    a, b, c, d = (rng.randint(-9, 9) for _ in range(4))
    ref = f"\\begin{{pmatrix}} {2 * a} & {2 * b} \\\\ {2 * c} & {2 * d} \\end{{pmatrix}}"
    ans = rng.choice([ref.replace("pmatrix", "bmatrix"), ref,
                      f"\\left[\\begin{{array}}{{cc}} {2 * a} & {2 * b} \\\\ {2 * c} & {2 * d} \\end{{array}}\\right]"])
    return (f"A 2 by 2 matrix has first row {a} and {b}, and second row {c} and {d}. Double every entry.", ref,
            "Multiply each entry by 2.", ans, rng.choice(["boxed", "think_boxed"]))


def _gen_vector(rng, strict=False):
    x, y, z = (rng.randint(-9, 9) for _ in range(3))
    ref = f"\\begin{{pmatrix}} {3 * x} \\\\ {3 * y} \\\\ {3 * z} \\end{{pmatrix}}"
    ans = rng.choice([ref, f"({3 * x}, {3 * y}, {3 * z})", f"\\langle {3 * x}, {3 * y}, {3 * z} \\rangle",
                      f"\\mathbf{{v}} = {ref}"])
    return (f"A vector has coordinates {x}, {y} and {z}. What is three times the vector?", ref,
            "Scale each coordinate.", ans, rng.choice(["boxed", "think_boxed"]))


_GENERATORS = (_gen_integer, _gen_negative, _gen_fraction, _gen_decimal, _gen_thousands, _gen_percent,
               _gen_sqrt, _gen_pi, _gen_set, _gen_interval, _gen_tuple, _gen_symbolic, _gen_equation,
               _gen_scientific, _gen_choice, _gen_factorial, _gen_abs, _gen_identity, _gen_negative_denominator,
               _gen_closed_form, _gen_number_words, _gen_repeating, _gen_spaced_thousands, _gen_retraction,
               _gen_plain_expression, _gen_matrix, _gen_vector)
_STRICT_AWARE = {_gen_factorial, _gen_abs, _gen_identity, _gen_negative_denominator, _gen_closed_form,
                 _gen_number_words, _gen_repeating, _gen_spaced_thousands, _gen_retraction, _gen_plain_expression,
                 _gen_matrix, _gen_vector}


def audit_problems(n: int, seed: int = 0, require_simplified: bool = False) -> list[AuditProblem]:
    """n seeded problems cycling through 27 answer kinds, each with a gold completion.

    With `require_simplified`, gold completions state simplified answers only (no 4!, \\binom{6}{3}).
    """
    rng = random.Random(seed)
    checker = MathVerifier(require_simplified=require_simplified)
    out: list[AuditProblem] = []
    seen: set = set()
    for k in range(n):
        gen = _GENERATORS[k % len(_GENERATORS)]
        for _attempt in range(50):
            drawn = gen(rng, require_simplified) if gen in _STRICT_AWARE else gen(rng)
            prompt, ref, reasoning, ans = drawn[:4]
            style = drawn[4] if len(drawn) > 4 else None
            keys = _answer_keys(parse_gold(ref))
            # answers must differ across problems (the audit uses other problems' golds as wrong
            # answers) and the prompt alone must not state the answer
            if keys & seen or checker.check(prompt, ref).score > 0:
                continue
            break
        seen |= keys
        out.append(AuditProblem(prompt=prompt, reference=ref, gold=_wrap_gold(rng, reasoning, ans, style)))
    return out


def _answer_keys(gold: Gold) -> set:
    v = gold.value
    if isinstance(v, Scalar) and v.frac is not None:
        return {v.frac, v.frac / 100} if v.percent else {v.frac}
    if isinstance(v, Relation) and isinstance(v.operands[-1], Scalar) and v.operands[-1].frac is not None:
        return {v.operands[-1].frac}
    return {gold.show()}
