"""Equivalence: is a parsed prediction the gold answer? Tolerance, sympy identity tests, sets,
tuples, intervals, equations, percent, and the "unevaluated expression" / "multiple answers"
outcomes. Policy: "Equivalence", "Percent", "Unevaluated arithmetic" and "Several candidate
answers" in the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

from verifiers.math_answer.guards import _sp
from verifiers.math_answer.values import Interval, IntervalUnion, Relation, Scalar, Seq, Text, _free_symbols_of


# --------------------------------------------------------------------------------------
# Comparison
# --------------------------------------------------------------------------------------


class _Outcome(Exception):
    """Short-circuit a comparison with a specific reason."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass
class _Cmp:
    rel_tol: float
    allow_unevaluated: bool
    probes: int = 5

    # -- scalars
    def scalars(self, p: Scalar, g: Scalar, check_literal: bool = True) -> bool:
        if p.percent != g.percent:
            pct, other = (p, g) if p.percent else (g, p)
            base = Scalar(pct.node, pct.frac, pct.inexact, pct.literal, False, pct._expr)
            scaled_node = ("pct", pct.node)
            scaled = Scalar(scaled_node, pct.frac / 100 if pct.frac is not None else None, pct.inexact, pct.literal, False)
            ok = self._scalar_eq(base, other) or self._scalar_eq(scaled, other)
        else:
            ok = self._scalar_eq(p, g)
        if ok and check_literal and not self.allow_unevaluated and g.literal and not p.literal and _is_rational(p):
            raise _Outcome("unevaluated expression")
        return ok

    def _scalar_eq(self, p: Scalar, g: Scalar) -> bool:
        if p.frac is not None and g.frac is not None:
            if p.frac == g.frac:
                return True
            if p.inexact or g.inexact:
                return abs(p.frac - g.frac) <= Fraction(self.rel_tol) * max(abs(p.frac), abs(g.frac))
            return False
        return self._sympy_eq(p.expr(), g.expr(), p.inexact or g.inexact)

    def _sympy_eq(self, a, b, inexact: bool) -> bool:
        sp = _sp()
        if a == b:
            return True
        if a.free_symbols != b.free_symbols:
            return False
        tol = self.rel_tol if inexact else 1e-20
        if not a.free_symbols:
            return self._num_close(a, b, tol, {})
        diff = a - b
        if diff == 0:
            return True
        try:
            if sp.expand(diff) == 0:
                return True
        except (TypeError, ValueError, ArithmeticError, AttributeError, NotImplementedError):
            pass
        symbols = sorted(a.free_symbols, key=lambda s: s.name)
        rng = random.Random(0x5EED)
        verdicts = []
        for _ in range(self.probes):
            point = {s: sp.Rational(rng.randint(1100, 2900), 1000) for s in symbols}
            verdicts.append(self._num_close(a, b, max(tol, 1e-25), point, strict=False))
        if all(v is True for v in verdicts):
            return True
        if any(v is False for v in verdicts):
            return False
        # inconclusive (evaluation undefined at the probe points): ask simplify
        try:
            return sp.simplify(diff) == 0
        except (TypeError, ValueError, ArithmeticError, AttributeError, NotImplementedError):
            return False

    def _num_close(self, a, b, tol: float, point: dict, strict: bool = True):
        """True/False when both sides evaluate to finite numbers, None when undefined."""
        sp = _sp()
        try:
            va = sp.N(a, 40, subs=point) if point else sp.N(a, 40)
            vb = sp.N(b, 40, subs=point) if point else sp.N(b, 40)
        except (TypeError, ValueError, ArithmeticError, AttributeError, NotImplementedError):
            return False if strict else None
        bad = (sp.nan, sp.zoo, sp.oo, -sp.oo)
        if va in bad or vb in bad or not va.is_number or not vb.is_number:
            if va == vb and va in (sp.oo, -sp.oo):
                return True
            return False if strict else None
        scale = max(abs(va), abs(vb))
        d = abs(va - vb)
        if scale == 0:
            return True
        return bool(d <= tol * scale)

    # -- any values
    def values(self, p: Any, g: Any) -> bool:
        if isinstance(g, Text) or isinstance(p, Text):
            return isinstance(g, Text) and isinstance(p, Text) and p.text == g.text and bool(g.text)
        # equations: compare right-hand sides unless both are equations
        if isinstance(g, Relation) and isinstance(p, Relation):
            return self._relations(p, g)
        if isinstance(p, Relation):
            if p.ops and all(op == "=" for op in p.ops):
                return self.values(p.operands[-1], g)
            iv = _inequality_to_interval(p)
            return iv is not None and self.values(iv, g)
        if isinstance(g, Relation):
            if all(op == "=" for op in g.ops):
                return self.values(p, g.operands[-1])
            iv = _inequality_to_interval(g)
            return iv is not None and self.values(p, iv)
        if isinstance(g, Scalar):
            if isinstance(p, Scalar):
                return self.scalars(p, g)
            if isinstance(p, Seq):
                distinct = self._distinct(p.items)
                if len(distinct) == 1:
                    return self.values(distinct[0], g)
                if len(distinct) > 1:
                    raise _Outcome("multiple answers")
            return False
        if isinstance(g, Seq):
            if isinstance(p, Scalar) or isinstance(p, Relation):
                return len(g.items) == 1 and self.values(p, g.items[0])
            if isinstance(p, Interval):
                return g.kind == "pair" and p.lo_open and p.hi_open and self._ordered(g.items, [p.lo, p.hi])
            if isinstance(p, Seq):
                if g.kind in ("tuple", "pair") or p.kind in ("tuple", "pair"):
                    if p.kind in ("set",) or g.kind == "set":
                        return False
                    return self._ordered(p.items, g.items)
                return self._unordered(p.items, g.items)
            return False
        if isinstance(g, Interval):
            if isinstance(p, Seq) and p.kind == "pair":
                return g.lo_open and g.hi_open and self._ordered(p.items, [g.lo, g.hi])
            if isinstance(p, IntervalUnion) and len(p.items) == 1:
                p = p.items[0]
            if isinstance(p, Interval):
                return (p.lo_open == g.lo_open and p.hi_open == g.hi_open
                        and self.scalars(p.lo, g.lo, False) and self.scalars(p.hi, g.hi, False))
            return False
        if isinstance(g, IntervalUnion):
            items = p.items if isinstance(p, IntervalUnion) else [p]
            items = [Interval(x.items[0], x.items[1], True, True) if isinstance(x, Seq) and x.kind == "pair" else x for x in items]
            if len(items) != len(g.items):
                return False
            return self._unordered(items, g.items)
        return False

    def _relations(self, p: Relation, g: Relation) -> bool:
        if p.ops != g.ops and not (len(p.ops) == len(g.ops) == 1 and _flip(p.ops[0]) == g.ops[0]):
            if all(op == "=" for op in p.ops) and all(op == "=" for op in g.ops):
                pass
            else:
                pi, gi = _inequality_to_interval(p), _inequality_to_interval(g)
                return pi is not None and gi is not None and self.values(pi, gi)
        if all(op == "=" for op in p.ops + g.ops):
            pl, pr = p.operands[0], p.operands[-1]
            gl, gr = g.operands[0], g.operands[-1]
            if self._same_symbol(pl, gl):
                return self.scalars(pr, gr, False)
            # general equations: lhs - rhs equal up to a non-zero constant factor
            sp = _sp()
            dp = pl.expr() - pr.expr()
            dg = gl.expr() - gr.expr()
            if dg == 0 or dp == 0:
                return dg == dp
            if self._sympy_eq(dp, dg, False) or self._sympy_eq(dp, -dg, False):
                return True
            ratio = sp.cancel(dp / dg)
            return bool(ratio.is_number and ratio != 0)
        pi, gi = _inequality_to_interval(p), _inequality_to_interval(g)
        return pi is not None and gi is not None and self.values(pi, gi)

    @staticmethod
    def _same_symbol(a: Scalar, b: Scalar) -> bool:
        return a.node[0] == "sym" and a.node == b.node

    def _distinct(self, items: list) -> list:
        out: list = []
        for x in items:
            if not any(self._safe_eq(x, y) for y in out):
                out.append(x)
        return out

    def _safe_eq(self, a: Any, b: Any) -> bool:
        try:
            return self.values(a, b)
        except _Outcome:
            return False

    def _ordered(self, ps: list, gs: list) -> bool:
        return len(ps) == len(gs) and all(self._item_eq(p, g) for p, g in zip(ps, gs))

    def _item_eq(self, p: Any, g: Any) -> bool:
        if isinstance(p, Scalar) and isinstance(g, Scalar):
            return self.scalars(p, g, False)
        return self.values(p, g)

    def _unordered(self, ps: list, gs: list) -> bool:
        ps, gs = self._distinct(ps), self._distinct(gs)
        if len(ps) != len(gs):
            return False
        remaining = list(gs)
        for p in ps:
            for j, g in enumerate(remaining):
                if self._safe_item_eq(p, g):
                    del remaining[j]
                    break
            else:
                return False
        return True

    def _safe_item_eq(self, p: Any, g: Any) -> bool:
        try:
            return self._item_eq(p, g)
        except _Outcome:
            return False


def _is_rational(v: Scalar) -> bool:
    if v.frac is not None:
        return True
    return bool(v.expr().is_Rational)


def _flip(op: str) -> str:
    return {"<": ">", ">": "<", "<=": ">=", ">=": "<=", "=": "=", "!=": "!="}[op]


def _inequality_to_interval(r: Relation) -> Interval | None:
    """x > 3, 3 < x, 1 < x <= 2 (one symbol) as an interval; None otherwise."""
    inf = Scalar(("const", "oo"), None, False, False)
    ninf = Scalar(("neg", ("const", "oo")), None, False, False)
    ops, xs = r.ops, r.operands
    if any(op not in ("<", ">", "<=", ">=") for op in ops):
        return None
    if len(ops) == 1:
        a, b = xs
        op = ops[0]
        if a.node[0] == "sym" and b.frac is not None or a.node[0] == "sym" and not _free_symbols_of(b):
            var, bound = a, b
        elif b.node[0] == "sym" and not _free_symbols_of(a):
            var, bound, op = b, a, _flip(op)
        else:
            return None
        if op in (">", ">="):
            return Interval(bound, inf, op == ">", True)
        return Interval(ninf, bound, True, op == "<")
    if len(ops) == 2 and xs[1].node[0] == "sym":
        lo, hi = xs[0], xs[2]
        if ops[0] in ("<", "<=") and ops[1] in ("<", "<="):
            return Interval(lo, hi, ops[0] == "<", ops[1] == "<")
        if ops[0] in (">", ">=") and ops[1] in (">", ">="):
            return Interval(hi, lo, ops[1] == ">", ops[0] == ">")
    return None
