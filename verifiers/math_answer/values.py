"""Values: parsed nodes as exact rationals (no sympy) or sympy objects (built under the size
guards), the value types compared by equivalence.py, and the parsed gold answer.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache
from typing import Any

from posttrain.verifiers.math_answer.extract import _find_boxed
from posttrain.verifiers.math_answer.guards import (
    DEFAULT_BUDGET, MAX_DIGITS, MAX_FACTORIAL, MAX_PM, Unparseable, _BudgetExceeded, _CallBudget, _sp,
)
from posttrain.verifiers.math_answer.normalize import (
    _CONNECTIVES, _CONST_WORDS, _FUNCS, _number_words, _unwrap_text_commands, clean_answer, parse_answer_text,
)


# --------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------


@dataclass
class Scalar:
    node: tuple
    frac: Fraction | None  # the value when it is rational and known without sympy
    inexact: bool  # written with decimals / scientific notation
    literal: bool  # a plain number literal (see the package docstring)
    percent: bool = False  # written with a percent sign (value kept without the /100)
    _expr: Any = None

    def expr(self):
        if self._expr is None:
            self._expr = _sp().Rational(self.frac.numerator, self.frac.denominator) if self.frac is not None else _to_sympy(self.node)
        return self._expr

    def show(self) -> str:
        if self.frac is not None:
            text = _fmt_frac(self.frac)
        else:
            text = _safe_str(self.expr())
        return text + ("%" if self.percent else "")


@dataclass
class Seq:
    kind: str  # list (bare commas, unordered), set, tuple (ordered), pair ("(a, b)": tuple or open interval)
    items: list
    has_or: bool = False

    def show(self) -> str:
        inner = ", ".join(v.show() for v in self.items)
        return {"set": "{%s}", "list": "%s", "tuple": "(%s)", "pair": "(%s)"}[self.kind] % inner if self.items else "{}"


@dataclass
class Interval:
    lo: Scalar
    hi: Scalar
    lo_open: bool
    hi_open: bool

    def show(self) -> str:
        return ("(" if self.lo_open else "[") + self.lo.show() + ", " + self.hi.show() + (")" if self.hi_open else "]")


@dataclass
class IntervalUnion:
    items: list

    def show(self) -> str:
        return " U ".join(v.show() for v in self.items)


@dataclass
class Relation:
    ops: list
    operands: list  # Scalars

    def show(self) -> str:
        out = self.operands[0].show()
        for op, v in zip(self.ops, self.operands[1:]):
            out += f" {op} {v.show()}"
        return out


@dataclass
class Matrix:
    rows: list  # rows of Scalars, rectangular

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.rows), len(self.rows[0])

    def show(self) -> str:
        return "[" + ", ".join("[" + ", ".join(v.show() for v in row) + "]" for row in self.rows) + "]"


@dataclass
class Text:
    text: str

    def show(self) -> str:
        return self.text


def _fmt_frac(f: Fraction) -> str:
    try:
        if f.denominator == 1:
            return str(f.numerator)
        return f"{f.numerator}/{f.denominator}"
    except ValueError:  # beyond Python's int -> str limit
        return f"<number with ~{max(_digits(f.numerator), _digits(f.denominator))} digits>"


def _safe_str(x: Any) -> str:
    try:
        s = str(x)
    except ValueError:  # an integer beyond Python's str conversion limit
        return "<very large number>"
    return s if len(s) <= 300 else s[:297] + "..."


def _digits(n: int) -> int:
    return max(1, int(abs(n).bit_length() * 0.30103) + 1)


def _check_power(base: Fraction, exp: int) -> None:
    size = max(_digits(base.numerator), _digits(base.denominator))
    if base not in (0, 1, -1) and abs(exp) * max(size - 1, 0.31) > MAX_DIGITS:
        raise Unparseable("number too large")
    if base == 0 and exp < 0:
        raise Unparseable("division by zero")


def _frac_eval(node: tuple) -> tuple[Fraction, bool] | None:
    """(value, inexact) when the node is rational and computable without sympy, else None."""
    kind = node[0]
    if kind == "num":
        text = node[1].rstrip(".")
        if len(text.replace(".", "")) > MAX_DIGITS:
            raise Unparseable("number too large")
        if "e" in text.lower():
            mant, _, ex = text.lower().partition("e")
            if abs(int(ex)) > MAX_DIGITS:
                raise Unparseable("number too large")
        return Fraction(text), ("." in text or "e" in text.lower())
    if kind == "mixed":
        whole, num, den = int(node[1]), int(node[2]), int(node[3])
        if den == 0:
            raise Unparseable("division by zero")
        return Fraction(whole) + Fraction(num, den), False
    if kind == "neg":
        inner = _frac_eval(node[1])
        return None if inner is None else (-inner[0], inner[1])
    if kind == "add":
        total, inexact = Fraction(0), False
        for sign, term in node[1]:
            if sign not in (1, -1):
                return None
            v = _frac_eval(term)
            if v is None:
                return None
            total += sign * v[0]
            inexact = inexact or v[1]
        return total, inexact
    if kind == "mul":
        total, inexact = Fraction(1), False
        for factor, power in node[1]:
            v = _frac_eval(factor)
            if v is None:
                return None
            if power == -1:
                if v[0] == 0:
                    raise Unparseable("division by zero")
                total /= v[0]
            else:
                total *= v[0]
            inexact = inexact or v[1]
        return total, inexact
    if kind == "pow":
        b = _frac_eval(node[1])
        e = _frac_eval(node[2])
        if b is None or e is None or e[0].denominator != 1:
            return None
        _check_power(b[0], e[0].numerator)
        return b[0] ** e[0].numerator, b[1] or e[1]
    if kind == "pct":
        v = _frac_eval(node[1])
        return None if v is None else (v[0] / 100, v[1])
    if kind in ("fact", "fact2"):
        v = _frac_eval(node[1])
        if v is None or v[0].denominator != 1 or v[0] < 0:
            return None
        if v[0] > MAX_FACTORIAL:
            raise Unparseable("number too large")
        n = int(v[0])
        return Fraction(math.factorial(n) if kind == "fact" else math.prod(range(n, 0, -2))), v[1]
    if kind == "binom":
        n, k = _frac_eval(node[1]), _frac_eval(node[2])
        if n is None or k is None or n[0].denominator != 1 or k[0].denominator != 1 or n[0] < 0:
            return None
        if n[0] > MAX_FACTORIAL:
            raise Unparseable("number too large")
        return Fraction(math.comb(int(n[0]), int(k[0])) if 0 <= k[0] <= n[0] else 0), False
    if kind == "abs":
        v = _frac_eval(node[1])
        return None if v is None else (abs(v[0]), v[1])
    return None


def _has_decimal(node: Any) -> bool:
    if isinstance(node, tuple):
        if node and node[0] == "num":
            return "." in node[1] or "e" in node[1].lower()
        return any(_has_decimal(x) for x in node)
    if isinstance(node, list):
        return any(_has_decimal(x) for x in node)
    return False


def _is_int_num(node: tuple) -> bool:
    return node[0] == "num" and node[1].isdigit()


def _is_literal(node: tuple) -> bool:
    kind = node[0]
    if kind in ("num", "mixed"):
        return True
    if kind in ("neg", "pct"):
        return _is_literal(node[1])
    if kind == "mul" and len(node[1]) == 2:
        (a, pa), (b, pb) = node[1]
        if pa == 1 and pb == -1:  # a/b, \frac{a}{b}, \frac{-3}{4}, \frac{3}{-4}
            a_inner = a[1] if a[0] == "neg" else a
            b_inner = b[1] if b[0] == "neg" else b
            return _is_int_num(a_inner) and _is_int_num(b_inner)
        if pa == 1 and pb == 1 and a[0] == "num" and b[0] == "pow":  # m x 10^k
            return _is_ten_power(b)
    if kind == "pow":
        return _is_ten_power(node)
    return False


def _is_ten_power(node: tuple) -> bool:
    if node[0] != "pow" or node[1] != ("num", "10"):
        return False
    e = node[2][1] if node[2][0] == "neg" else node[2]
    return _is_int_num(e)


def _to_sympy(node: tuple):
    """Build a sympy object from a scalar node, refusing numbers that would not fit."""
    sp = _sp()
    kind = node[0]
    fr = _frac_eval(node) if kind in ("num", "mixed", "neg", "add", "mul", "pow", "fact", "fact2", "binom", "pct") else None
    if fr is not None:
        return sp.Rational(fr[0].numerator, fr[0].denominator)
    if kind == "sym":
        return sp.Symbol(node[1])
    if kind == "const":
        return {"pi": sp.pi, "E": sp.E, "I": sp.I, "oo": sp.oo}[node[1]]
    if kind == "neg":
        return -_to_sympy(node[1])
    if kind == "add":
        out = sp.Integer(0)
        for sign, term in node[1]:
            if sign not in (1, -1):
                raise Unparseable("misplaced \\pm")
            out = out + sign * _to_sympy(term)
        return out
    if kind == "mul":
        out = sp.Integer(1)
        for factor, power in node[1]:
            v = _to_sympy(factor)
            if power == -1:
                if v == 0:
                    raise Unparseable("division by zero")
                out = out / v
            else:
                out = out * v
        return out
    if kind == "pow":
        base = _to_sympy(node[1])
        exp = _to_sympy(node[2])
        if exp.is_Number and base.is_Number:
            if exp.is_Integer:
                _check_power(Fraction(int(base.p), int(base.q)) if base.is_Rational else Fraction(2), int(exp))
            elif abs(exp) > MAX_DIGITS:
                raise Unparseable("number too large")
        elif exp.is_Number and abs(exp) > MAX_DIGITS:
            raise Unparseable("exponent too large")
        elif not exp.is_Number and exp.free_symbols == set() and base.is_Number and abs(base) > 1:
            approx = sp.N(exp, 15)
            if approx.is_real and abs(approx) * _digits(int(abs(base))) > MAX_DIGITS:
                raise Unparseable("number too large")
        return sp.Pow(base, exp)
    if kind == "func":
        _, name, arg_node, base_node = node
        arg = _to_sympy(arg_node)
        if name == "sqrt":
            return sp.sqrt(arg)
        if name in ("log", "ln", "lg"):
            if base_node is not None:
                return sp.log(arg, _to_sympy(base_node))
            if name == "lg":
                return sp.log(arg, 10)
            return sp.log(arg)
        fn = {"sin": sp.sin, "cos": sp.cos, "tan": sp.tan, "sec": sp.sec, "csc": sp.csc, "cot": sp.cot,
              "arcsin": sp.asin, "asin": sp.asin, "arccos": sp.acos, "acos": sp.acos, "arctan": sp.atan,
              "atan": sp.atan, "sinh": sp.sinh, "cosh": sp.cosh, "tanh": sp.tanh, "exp": sp.exp,
              "abs": sp.Abs}[name]
        return fn(arg)
    if kind == "root":
        n = _to_sympy(node[2])
        if n.is_Number and abs(n) > MAX_DIGITS:
            raise Unparseable("root index too large")
        arg = _to_sympy(node[1])
        if n.is_Integer and n % 2 == 1 and arg.is_number and arg.is_extended_negative:
            return -sp.root(-arg, n)  # \sqrt[3]{-8} is the real root -2, as a grader reads it
        return sp.root(arg, n)
    if kind == "abs":
        return sp.Abs(_to_sympy(node[1]))
    if kind in ("fact", "fact2"):
        v = _to_sympy(node[1])
        if v.is_Number and (not v.is_Integer or v > MAX_FACTORIAL):
            raise Unparseable("factorial out of range")
        return sp.factorial(v) if kind == "fact" else sp.factorial2(v)
    if kind == "binom":
        return sp.binomial(_to_sympy(node[1]), _to_sympy(node[2]))
    if kind == "pct":
        return _to_sympy(node[1]) / 100
    raise Unparseable(f"not a number or expression: {kind}")


def _count_pm(node: Any) -> int:
    if isinstance(node, tuple) and not (node and isinstance(node[0], str)):
        return sum(_count_pm(x) for x in node)  # a (factor, power) pair
    if isinstance(node, tuple):
        n = 1 if node and node[0] == "pm" else 0
        if node and node[0] == "add":
            n += sum(1 for sign, _ in node[1] if sign in ("pm", "mp"))
        return n + sum(_count_pm(x) for x in node[1:])
    if isinstance(node, list):
        return sum(_count_pm(x) for x in node)
    return 0


def _expand_pm(node: Any) -> list:
    """All sign choices of the \\pm / \\mp in a node (one node when there is none)."""
    if isinstance(node, (list, tuple)) and not (node and isinstance(node[0], str)):
        combos: list[list] = [[]]  # a list of nodes, or a (factor, power) pair
        for x in node:
            combos = [c + [alt] for c in combos for alt in _expand_pm(x)]
        return [type(node)(c) for c in combos]
    if not isinstance(node, tuple) or not node:
        return [node]
    kind = node[0]
    if kind == "pm":
        return [alt for inner in _expand_pm(node[1]) for alt in (inner, ("neg", inner))]
    if kind == "add":
        options: list[list] = [[]]
        for sign, term in node[1]:
            signs = (1, -1) if sign in ("pm", "mp") else (sign,)
            options = [o + [(sg, t)] for o in options for sg in signs for t in _expand_pm(term)]
        return [("add", o) for o in options]
    if kind in ("num", "sym", "const"):
        return [node]
    parts = [_expand_pm(x) if isinstance(x, (tuple, list)) else [x] for x in node[1:]]
    combos = [[]]
    for alts in parts:
        combos = [c + [a] for c in combos for a in alts]
    return [(kind, *c) for c in combos]


def _scalar(node: tuple) -> Scalar:
    percent = False
    if node[0] == "pct":
        percent, node = True, node[1]
    fr = _frac_eval(node)
    if fr is not None:
        return Scalar(node, fr[0], fr[1], _is_literal(node), percent)
    return Scalar(node, None, _has_decimal(node), False, percent)


def build_value(node: tuple) -> Any:
    """Turn a parsed node into a value (Scalar, Seq, Interval, IntervalUnion, Relation)."""
    kind = node[0]
    if kind == "seq":
        _, skind, items, has_or = node
        return Seq(skind, [build_value(x) for x in items], has_or)
    if kind == "interval":
        _, lo, hi, lo_open, hi_open = node
        lo_v, hi_v = build_value(lo), build_value(hi)
        if not isinstance(lo_v, Scalar) or not isinstance(hi_v, Scalar):
            raise Unparseable("interval endpoints must be numbers")
        return Interval(lo_v, hi_v, lo_open, hi_open)
    if kind == "union":
        parts = [build_value(x) for x in node[1]]
        out = []
        for p in parts:
            if isinstance(p, Seq) and p.kind == "pair":
                p = Interval(p.items[0], p.items[1], True, True)
            if not isinstance(p, Interval):
                raise Unparseable("union of non-intervals")
            out.append(p)
        return IntervalUnion(out)
    if kind == "matrix":
        rows = [[build_value(x) for x in row] for row in node[1]]
        if not all(isinstance(v, Scalar) for row in rows for v in row):
            raise Unparseable("matrix entries must be numbers or expressions")
        return Matrix(rows)
    if kind == "rel":
        _, ops, operands = node
        if all(op == "=" for op in ops) and operands[-1][0] in ("matrix", "seq"):
            # \mathbf{v} = \begin{pmatrix}...\end{pmatrix}, (x, y) = (1, 2): the value is the right-hand side
            return build_value(operands[-1])
        n_pm = _count_pm(node)
        if n_pm:  # x = (-b \pm \sqrt{d}) / 2a: one relation per sign choice
            if n_pm > MAX_PM:
                raise Unparseable("too many \\pm")
            return Seq("set", [build_value(alt) for alt in _expand_pm(node)], has_or=True)
        vals = [build_value(x) for x in operands]
        if not all(isinstance(v, Scalar) for v in vals):
            raise Unparseable("relation between non-numbers")
        return Relation(list(ops), vals)
    n_pm = _count_pm(node)
    if n_pm:
        if n_pm > MAX_PM:
            raise Unparseable("too many \\pm")
        alts = [_scalar(a) for a in _expand_pm(node)]
        return Seq("set", alts, has_or=True)
    return _scalar(node)


def _free_symbols_of(v: Any) -> set:
    if isinstance(v, Scalar):
        if v.frac is not None:
            return set()
        return {s.name for s in v.expr().free_symbols}
    if isinstance(v, Seq):
        return set().union(*[_free_symbols_of(x) for x in v.items]) if v.items else set()
    if isinstance(v, Interval):
        return _free_symbols_of(v.lo) | _free_symbols_of(v.hi)
    if isinstance(v, IntervalUnion):
        return set().union(*[_free_symbols_of(x) for x in v.items])
    if isinstance(v, Relation):
        return set().union(*[_free_symbols_of(x) for x in v.operands])
    if isinstance(v, Matrix):
        return set().union(*[_free_symbols_of(x) for row in v.rows for x in row])
    return set()


def _text_key(s: str) -> str:
    s = _unwrap_text_commands(s)
    s = re.sub(r"\\[A-Za-z]+", " ", s)
    return re.sub(r"[^0-9a-z]+", "", s.lower())


# --------------------------------------------------------------------------------------
# The gold answer
# --------------------------------------------------------------------------------------


@dataclass
class Gold:
    raw: str
    value: Any  # a value, or Text for text answers
    numeric: bool  # no free symbols
    sequence: bool  # a tuple / set / list / interval: thousands separators stay commas

    def show(self) -> str:
        return self.value.show()


def _looks_like_text(s: str) -> bool:
    stripped = _unwrap_text_commands(s).strip()
    words = re.findall(r"[A-Za-z]+", stripped)
    if not words or re.search(r"[\d\\^=+*/|]", stripped):
        return False
    if not re.search(r"[A-Za-z]", _number_words(stripped)):
        return False  # "forty-two" is a number
    return any(len(w) >= 2 and w.lower() not in _FUNCS and w.lower() not in _CONST_WORDS
               and w.lower() not in _CONNECTIVES for w in words)


@lru_cache(maxsize=8192)
def parse_gold(reference: str, budget: int = DEFAULT_BUDGET) -> Gold:
    """Parse a gold answer; ValueError when it cannot be read (a bug in the problem set)."""
    raw = reference.strip()
    if not raw:
        raise ValueError("malformed reference: empty gold answer")
    if "\\boxed" in raw or "\\fbox" in raw:
        boxed = _find_boxed(raw)
        if boxed:
            raw = boxed[-1].value.strip()
    if _looks_like_text(raw):
        return Gold(raw, Text(_text_key(raw)), True, False)
    try:
        with _CallBudget(budget):
            cleaned = clean_answer(raw, merge_thousands=True)
            env = re.search(r"\\begin\s*\{\s*([A-Za-z*]+)\s*\}", cleaned)
            if env is not None:
                raise ValueError(f"unsupported reference {reference!r}: the \\begin{{{env.group(1)}}} environment is "
                                 "not supported (matrices: pmatrix, bmatrix, Bmatrix, matrix, smallmatrix, array)")
            node = parse_answer_text(cleaned)
            value = build_value(node)
            if isinstance(value, (Seq, Interval, IntervalUnion, Matrix)):
                # re-read without merging "1,234" so a tuple (1,234) stays a tuple
                node = parse_answer_text(clean_answer(raw, merge_thousands=False))
                value = build_value(node)
            numeric = not _free_symbols_of(value)
    except Unparseable as e:
        raise ValueError(f"malformed reference {reference!r}: {e}") from None
    except _BudgetExceeded:
        raise ValueError(f"malformed reference {reference!r}: too expensive to parse") from None
    except RecursionError:
        raise ValueError(f"malformed reference {reference!r}: nested too deeply") from None
    sequence = isinstance(value, (Seq, Interval, IntervalUnion, Matrix))
    return Gold(raw, value, numeric, sequence)
