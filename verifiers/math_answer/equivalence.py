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

from posttrain.verifiers.math_answer.guards import _sp
from posttrain.verifiers.math_answer.values import (
    Interval, IntervalUnion, Matrix, Relation, Scalar, Seq, Text, _free_symbols_of,
)

_PROBE_POINTS = 16  # candidate points per comparison (critical points first, then seeded random ones)
_PROBE_ENOUGH = 6  # stop after this many points where both sides are defined and agree
_PROBE_MIN = 3  # fewer valid points than this: inconclusive (sympy's simplify decides)


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
    require_simplified: bool = False

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
        if ok and check_literal and self.require_simplified and g.literal and not p.literal and _is_rational(p):
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
        tol = self.rel_tol if inexact else 1e-20
        # the union: "\cosh^2 u - \sinh^2 u" (symbol u) is the constant 1
        symbols = sorted(a.free_symbols | b.free_symbols, key=lambda s: s.name)
        if not symbols:
            return self._num_close(a, b, tol, {})
        diff = a - b
        if diff == 0:
            return True
        try:
            if sp.expand(diff) == 0:
                return True
        except (TypeError, ValueError, ArithmeticError, AttributeError, NotImplementedError):
            pass
        verdict = self._probe(a, b, symbols, max(tol, 1e-25))
        if verdict is not None:
            return verdict
        # inconclusive (too few points where both sides are defined): ask simplify
        try:
            return sp.simplify(diff) == 0
        except (TypeError, ValueError, ArithmeticError, AttributeError, NotImplementedError):
            return False

    def _probe(self, a, b, symbols: list, tol: float):
        """Compare a and b at seeded points where both are defined (real-valued, every square
        root / log / power argument in its real domain): True after enough agreeing points,
        False at the first point where they differ, None when too few points were valid.

        The points mix signs and magnitudes and are never integers; for one variable, points
        between and beyond the real roots of each |.|, root, power or log argument come first,
        so identities that hold only on part of the line (sqrt(t^2) = t, |t| = t) are refuted.
        """
        sp = _sp()
        real = not (a.has(sp.I) or b.has(sp.I))
        checks = _domain_checks(a) + _domain_checks(b) if real else []
        points = _critical_points(checks, symbols) + _random_points(symbols, _PROBE_POINTS)
        valid = 0
        for point in points[:_PROBE_POINTS + 8]:
            if real and not _in_domain(checks, point):
                continue
            verdict = self._num_close(a, b, tol, point, strict=False, real=real)
            if verdict is None:
                continue
            if verdict is False:
                return False
            valid += 1
            if valid >= _PROBE_ENOUGH:
                return True
        return True if valid >= _PROBE_MIN else None

    def _num_close(self, a, b, tol: float, point: dict, strict: bool = True, real: bool = False):
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
        if real and point:
            ia, ib = abs(sp.im(va)), abs(sp.im(vb))
            if ia > 1e-30 * max(1, abs(va)) or ib > 1e-30 * max(1, abs(vb)):
                return None  # complex on the real line: outside the domain
        scale = max(abs(va), abs(vb))
        d = abs(va - vb)
        if scale == 0:
            return True
        if point and scale < 1e-30:
            return True  # both vanish at this point to working precision (sin^2 x + cos^2 x - 1 vs 0)
        return bool(d <= tol * scale)

    # -- any values
    def values(self, p: Any, g: Any) -> bool:
        if isinstance(g, Text) or isinstance(p, Text):
            return isinstance(g, Text) and isinstance(p, Text) and p.text == g.text and bool(g.text)
        if isinstance(g, Matrix) or isinstance(p, Matrix):
            return self._matrices(p, g)
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

    def _matrices(self, p: Any, g: Any) -> bool:
        """Entrywise, same shape; a row or column vector also equals an ordered tuple of its entries."""
        if isinstance(p, Relation) and all(op == "=" for op in p.ops):
            p = p.operands[-1]
        pe, ge = _matrix_entries(p), _matrix_entries(g)
        if pe is None or ge is None:
            return False
        (pshape, pitems), (gshape, gitems) = pe, ge
        if pshape is None and gshape is None:
            return False
        if pshape != gshape:
            other = gshape if pshape is None else pshape if gshape is None else None
            if other is None or other[0] != "vector":
                return False  # different shapes; a tuple matches only a row or column vector
        return len(pitems) == len(gitems) and all(self.scalars(x, y) for x, y in zip(pitems, gitems))

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


def _matrix_entries(v: Any):
    """(shape, entries) of a matrix, (None, entries) of a vector written as a tuple, else None."""
    if isinstance(v, Matrix):
        shape = v.shape
        if shape[0] != 1 and shape[1] != 1:
            return shape, [x for row in v.rows for x in row]
        # a vector: a tuple of the same entries matches it in either orientation
        return ("vector", shape), [x for row in v.rows for x in row]
    if isinstance(v, Seq) and v.kind in ("tuple", "pair") and all(isinstance(x, Scalar) for x in v.items):
        return None, list(v.items)
    return None


def _domain_checks(expr) -> list:
    """(kind, argument) for each node whose real domain is restricted and whose argument has symbols."""
    sp = _sp()
    out = []
    for node in sp.preorder_traversal(expr):
        if node.is_Pow:
            base, exp = node.args
            if not exp.is_Integer and base.free_symbols:
                out.append(("pos" if exp.is_negative else "nonneg", base))
            if not exp.is_number and exp.free_symbols:
                out.append(("pos", base))
        elif node.func in (sp.log,) and node.args[0].free_symbols:
            out.append(("pos", node.args[0]))
        elif node.func in (sp.asin, sp.acos) and node.args[0].free_symbols:
            out.append(("unit", node.args[0]))
        elif node.func is sp.acosh and node.args[0].free_symbols:
            out.append(("ge1", node.args[0]))
        elif node.func is sp.atanh and node.args[0].free_symbols:
            out.append(("in1", node.args[0]))
        elif node.func in (sp.Abs, sp.sign) and node.args[0].free_symbols:
            out.append(("any", node.args[0]))  # no restriction, but its roots are critical points
        if len(out) > 12:
            break
    return out


def _in_domain(checks: list, point: dict) -> bool:
    sp = _sp()
    for kind, arg in checks:
        if kind == "any":
            continue
        try:
            v = sp.N(arg, 30, subs=point)
        except (TypeError, ValueError, ArithmeticError, AttributeError, NotImplementedError):
            return False
        if not v.is_number or v in (sp.nan, sp.zoo, sp.oo, -sp.oo):
            return False
        if abs(sp.im(v)) > 1e-25 * max(1, abs(v)):
            return False
        v = sp.re(v)
        if (kind == "pos" and not v > 0 or kind == "nonneg" and not v >= 0 or kind == "unit" and not abs(v) <= 1
                or kind == "ge1" and not v >= 1 or kind == "in1" and not abs(v) < 1):
            return False
    return True


def _critical_points(checks: list, symbols: list) -> list:
    """For one variable: points between and beyond the real roots of the restricted arguments."""
    if len(symbols) != 1 or not checks:
        return []
    sp = _sp()
    x = symbols[0]
    roots: set = set()
    for _, arg in checks[:6]:
        try:
            num, _den = sp.fraction(sp.together(arg))
            for part in (num, _den):
                if not part.free_symbols:
                    continue
                poly = sp.Poly(part, x)
                if poly.degree() < 1 or poly.degree() > 8 or not poly.is_univariate:
                    continue
                for r in poly.sqf_part().nroots(n=15, maxsteps=60):  # square-free: simple roots converge
                    if abs(sp.im(r)) < 1e-9:
                        roots.add(round(float(sp.re(r)), 9))
        except Exception:  # noqa: BLE001  (sympy / mpmath raise many kinds; no critical points then)
            continue
    if not roots:
        return []
    ordered = sorted(roots)[:8]
    cuts = [ordered[0] - 1.0137] + [(u + v) / 2 + 0.0137 * (v - u) for u, v in zip(ordered, ordered[1:])]
    cuts.append(ordered[-1] + 1.0137)
    return [{x: sp.Rational(round(c * 10000), 10000)} for c in cuts]


def _random_points(symbols: list, n: int) -> list:
    """Seeded points: every sign pattern of the first four variables, small then larger magnitudes,
    never integers (odd numerators over 1000)."""
    sp = _sp()
    rng = random.Random(0x5EED)
    points = []
    for i in range(n):
        point = {}
        for j, sym in enumerate(symbols):
            negative = (i >> j) & 1 if j < 4 else rng.random() < 0.5
            mag = rng.randrange(151, 2950, 2) if i < n // 2 else rng.randrange(3001, 12000, 2)
            point[sym] = sp.Rational(-mag if negative else mag, 1000)
        points.append(point)
    # interleave so that every sign pattern is met early and both magnitude ranges are tried
    half = n // 2
    return [p for pair in zip(points[:half], points[half:]) for p in pair] + points[2 * half:]


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
