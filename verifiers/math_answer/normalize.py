"""Normalisation: LaTeX / unicode / percent / thousands clean-up, then our own tokenizer and
parser (no `eval`) that turns an answer into node tuples; trailing units and words are dropped
there. Policy: "Normalisation" in the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from verifiers.math_answer.extract import _match_brace
from verifiers.math_answer.guards import MAX_ITEMS, Unparseable


# --------------------------------------------------------------------------------------
# Normalisation: LaTeX / unicode clean-up to a compact string our tokenizer reads
# --------------------------------------------------------------------------------------

_UNICODE = {
    "\u2212": "-", "\u2013": "-", "\u2014": "-", "\u2012": "-", "\ufe63": "-", "\uff0d": "-",
    "\u00d7": r" \times ", "\u00b7": r" \cdot ", "\u22c5": r" \cdot ", "\u2219": r" \cdot ",
    "\u00f7": r" \div ", "\u221a": r"\sqrt ", "\u03c0": r"\pi ", "\u221e": r"\infty ",
    "\u2264": r" \le ", "\u2265": r" \ge ", "\u2260": r" \ne ", "\u00b1": r" \pm ", "\u2213": r" \mp ",
    "\u222a": r" \cup ", "\u2205": r" \emptyset ", "\u00b0": "", "\u00b2": "^2", "\u00b3": "^3",
    "\u00b9": "^1", "\u2070": "^0", "\u2074": "^4", "\u2075": "^5", "\u2076": "^6", "\u2077": "^7",
    "\u2078": "^8", "\u2079": "^9", "\u00bd": r"\frac{1}{2}", "\u00bc": r"\frac{1}{4}",
    "\u00be": r"\frac{3}{4}", "\u2153": r"\frac{1}{3}", "\u2154": r"\frac{2}{3}",
    "\u00a0": " ", "\u2009": " ", "\u202f": " ", "\u2002": " ", "\u2003": " ", "\uff0c": ",",
    "\uff1a": ":", "\u2018": "'", "\u2019": "'", "\u201c": '"', "\u201d": '"', "\u2026": r" \dots ",
}
_UNICODE_RE = re.compile("|".join(re.escape(k) for k in _UNICODE))
_TEXT_CMDS = ("text", "textbf", "textit", "textrm", "textsf", "texttt", "mathrm", "mathbf", "mathit",
              "mathsf", "mathtt", "mbox", "hbox", "operatorname", "boxed", "fbox", "mathbb", "bm",
              "boldsymbol", "emph", "underline", "overline")
_TEXT_CMD_RE = re.compile(r"\\(?:%s)\s*\{" % "|".join(_TEXT_CMDS))
_SIZING_RE = re.compile(r"\\(?:left|right|bigl|bigr|Bigl|Bigr|biggl|biggr|Biggl|Biggr|big|Big|bigg|Bigg)(?![A-Za-z])\s*\.?")
_SPACES_RE = re.compile(r"\\(?:quad|qquad|displaystyle|textstyle|scriptstyle|limits|nolimits|[,;:! ])|~")


def _unwrap_text_commands(s: str) -> str:
    for _ in range(50):
        m = _TEXT_CMD_RE.search(s)
        if not m:
            return s
        close = _match_brace(s, m.end() - 1)
        if close is None:
            s = s[: m.start()] + " " + s[m.end():]
        else:
            s = s[: m.start()] + " " + s[m.end():close] + " " + s[close + 1:]
    return s


def clean_answer(s: str, merge_thousands: bool = True) -> str:
    """Normalise the surface of an extracted answer (see the package docstring)."""
    s = _UNICODE_RE.sub(lambda m: _UNICODE[m.group(0)], s)
    s = s.replace("`", " ")
    s = _unwrap_text_commands(s)
    s = _SIZING_RE.sub(" ", s)
    s = re.sub(r"\\[dtc]frac(?![A-Za-z])", r"\\frac", s)
    s = re.sub(r"\\frac\s*(\d)\s*(\d)", r"\\frac{\1}{\2}", s)
    s = re.sub(r"\\frac\s*(\d)\s*\{", r"\\frac{\1}{", s)
    s = re.sub(r"\\frac\s*\{([^{}]*)\}\s*(\d)", r"\\frac{\1}{\2}", s)
    s = re.sub(r"\\sqrt\s*(\d)", r"\\sqrt{\1}", s)
    s = re.sub(r"\^\s*\{\s*\\circ\s*\}|\^\s*\\circ|\\circ|\\degree", " ", s)
    s = s.replace("\\%", "%")
    s = re.sub(r"(?i)(?<=[\d}])\s*(?:percent(?:age)?|pct)\b", "%", s)
    s = re.sub(r"\\\$|\$", " ", s)
    s = re.sub(r"\\[()\[\]]", " ", s)
    s = s.replace("{,}", "")
    s = re.sub(r"(\d)\\,(?=\d{3}(?!\d))", r"\1", s)
    s = _SPACES_RE.sub(" ", s)
    s = re.sub(r"(?<=[\w)}])\*\*(?=[\w({])", "^", s)
    s = s.replace("**", " ").replace("__", " ")
    if merge_thousands:
        s = re.sub(r"(?<![\d.,])\d{1,3}(?:,\d{3})+(?![\d,])", lambda m: m.group(0).replace(",", ""), s)
        s = re.sub(r"(?<![\d.])\d{1,3}(?: \d{3})+(?![\d.])", lambda m: m.group(0).replace(" ", ""), s)
    s = re.sub(r"[\s.,;:!?]+$", "", s)
    s = re.sub(r"^[\s:,;]+", "", s)
    s = re.sub(r"\s+", " ", s)
    return s


# --------------------------------------------------------------------------------------
# Tokenizer and parser (no eval): text -> small AST
# --------------------------------------------------------------------------------------

_TOKEN_RE = re.compile(
    r"(?P<ws>\s+)"
    r"|(?P<num>(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+(?![A-Za-z0-9]))?)"
    r"|(?P<cmd>\\(?:[A-Za-z]+|[{}|]))"
    r"|(?P<word>[A-Za-z]+(?:'[A-Za-z]+)?)"
    r"|(?P<op>\*\*|<=|>=|!=|==|[-+*/^!%=<>(),;\[\]{}|_:&])"
    r"|(?P<junk>.)",
    re.S,
)
_FUNCS = {"sin", "cos", "tan", "sec", "csc", "cot", "arcsin", "arccos", "arctan", "asin", "acos",
          "atan", "sinh", "cosh", "tanh", "log", "ln", "exp", "sqrt", "abs", "lg"}
_CONST_WORDS = {"pi": "pi", "inf": "oo", "infty": "oo", "infinity": "oo", "oo": "oo"}
_CONNECTIVES = {"or", "and", "either"}
_NEGATIONS = {"not", "no", "never", "isnt", "cannot", "neither", "nor", "none", "dont", "doesnt", "cant",
              "wont", "arent", "wasnt"}
_SHORT_WORDS = {"an", "as", "at", "be", "by", "do", "go", "he", "if", "in", "is", "it", "me", "my", "of",
                "on", "so", "to", "up", "us", "we", "are", "but", "can", "for", "has", "its", "may",
                "now", "one", "our", "the", "was", "who", "why", "yes", "you", "all", "any", "get",
                "got", "let", "see", "use", "two", "six", "ten", "per", "cm", "mm", "km", "kg", "mg",
                "ml", "lb", "lbs", "oz", "ft", "yd", "mi", "hr", "hrs", "min", "sec", "mph", "kmh",
                "usd", "eur", "gbp", "deg", "rad", "sq", "cu", "pct", "rs", "th", "nd", "rd", "st",
                "am", "pm", "cents", "and", "or", "not", "no", "nor", "yes", "ok"}
_UNIT_LETTER_EXCLUDE = {"x", "y", "z", "n", "k"}
_GREEK = {"alpha", "beta", "gamma", "delta", "epsilon", "varepsilon", "zeta", "eta", "theta", "vartheta",
          "iota", "kappa", "lambda", "mu", "nu", "xi", "rho", "sigma", "tau", "upsilon", "phi",
          "varphi", "chi", "psi", "omega", "Gamma", "Delta", "Theta", "Lambda", "Xi", "Sigma",
          "Upsilon", "Phi", "Psi", "Omega"}
_CMD_MAP = {
    "cdot": ("op", "*"), "times": ("op", "*"), "ast": ("op", "*"), "div": ("op", "/"),
    "pm": ("op", "pm"), "mp": ("op", "mp"), "le": ("op", "<="), "leq": ("op", "<="),
    "leqslant": ("op", "<="), "ge": ("op", ">="), "geq": ("op", ">="), "geqslant": ("op", ">="),
    "lt": ("op", "<"), "gt": ("op", ">"), "ne": ("op", "!="), "neq": ("op", "!="),
    "approx": ("op", "="), "simeq": ("op", "="), "cup": ("op", "cup"), "lor": ("conn", "or"),
    "vee": ("conn", "or"), "land": ("conn", "and"), "wedge": ("conn", "and"),
    "{": ("op", "\\{"), "}": ("op", "\\}"), "|": ("op", "|"), "lvert": ("op", "|"),
    "rvert": ("op", "|"), "vert": ("op", "|"), "mid": ("op", "|"), "emptyset": ("empty", ""),
    "varnothing": ("empty", ""), "infty": ("const", "oo"), "pi": ("const", "pi"),
    "frac": ("cmd", "frac"), "sqrt": ("cmd", "sqrt"), "binom": ("cmd", "binom"),
    "dbinom": ("cmd", "binom"), "tbinom": ("cmd", "binom"), "lbrace": ("op", "\\{"),
    "rbrace": ("op", "\\}"), "langle": ("op", "("), "rangle": ("op", ")"), "in": ("op", "in"),
}


@dataclass(frozen=True)
class _Tok:
    kind: str  # num sym const func cmd op conn word empty junk
    text: str


def tokenize(s: str, numeric_mode: bool = False) -> list[_Tok]:
    toks: list[_Tok] = []
    for m in _TOKEN_RE.finditer(s):
        kind = m.lastgroup
        t = m.group(kind)
        if kind == "ws":
            continue
        if kind == "num":
            toks.append(_Tok("num", t))
        elif kind == "cmd":
            name = t[1:]
            if name in _CMD_MAP:
                k, v = _CMD_MAP[name]
                toks.append(_Tok(k, v))
            elif name in _FUNCS:
                toks.append(_Tok("func", name))
            elif name in _GREEK:
                toks.append(_Tok("sym", name))
            else:
                toks.append(_Tok("junk", t))
        elif kind == "word":
            low = t.lower()
            if low in _CONST_WORDS and (t == low or len(t) > 2):
                toks.append(_Tok("const", _CONST_WORDS[low]))
            elif low in _FUNCS:
                toks.append(_Tok("func", low))
            elif low in _CONNECTIVES:
                toks.append(_Tok("conn", low))
            elif len(t) == 1:
                if t == "e":
                    toks.append(_Tok("const", "E"))
                elif t == "i":
                    toks.append(_Tok("const", "I"))
                elif numeric_mode and t.lower() not in _UNIT_LETTER_EXCLUDE:
                    toks.append(_Tok("word", t))
                else:
                    toks.append(_Tok("sym", t))
            elif len(t) <= 3 and t.isalpha() and low not in _SHORT_WORDS and not numeric_mode:
                toks.extend(_Tok("sym", c) if c not in "ei" else _Tok("const", "E" if c == "e" else "I") for c in t)
            else:
                toks.append(_Tok("word", t))
        elif kind == "op":
            toks.append(_Tok("op", "^" if t == "**" else ("=" if t == "==" else t)))
        else:
            toks.append(_Tok("junk", t))
    return toks


_ITEM_START_KINDS = {"num", "sym", "const", "func", "cmd", "empty"}
_ITEM_START_OPS = {"(", "[", "{", "\\{", "-", "+", "pm", "mp", "|"}
_IMPLICIT_KINDS = {"sym", "const", "func", "cmd"}
_REL_OPS = {"=", "<", ">", "<=", ">=", "!="}


class _Parser:
    """Recursive descent over the tokens; builds tuples (node kinds: see `_frac_eval` and `_to_sympy`)."""

    def __init__(self, toks: list[_Tok], numeric_mode: bool):
        self.t = toks
        self.i = 0
        self.numeric_mode = numeric_mode

    # -- helpers
    def peek(self, k: int = 0) -> _Tok | None:
        j = self.i + k
        return self.t[j] if j < len(self.t) else None

    def is_op(self, text: str, k: int = 0) -> bool:
        tok = self.peek(k)
        return tok is not None and tok.kind == "op" and tok.text == text

    def take(self) -> _Tok:
        tok = self.peek()
        if tok is None:
            raise Unparseable("unexpected end of answer")
        self.i += 1
        return tok

    def expect(self, text: str) -> None:
        tok = self.take()
        if tok.kind != "op" or tok.text != text:
            raise Unparseable(f"expected {text!r}, found {tok.text!r}")

    def starts_item(self, k: int = 0) -> bool:
        tok = self.peek(k)
        if tok is None:
            return False
        return tok.kind in _ITEM_START_KINDS or (tok.kind == "op" and tok.text in _ITEM_START_OPS)

    def _pronoun_or_article(self) -> bool:
        """"I think ...", "a total of ...": a leading I / a / A followed by a word is English."""
        tok, nxt = self.peek(), self.peek(1)
        return (tok is not None and tok.kind == "sym" and tok.text in ("I", "a", "A")
                and nxt is not None and nxt.kind == "word")

    # -- grammar
    def parse_answer(self) -> tuple:
        skipped_words = False
        while self.peek() is not None and (self.peek().kind == "word" or (self.peek().kind == "conn" and self.peek().text == "either")
                                           or self._pronoun_or_article()):
            word = self.take().text.lower().replace("'", "")
            if word in _NEGATIONS:
                raise Unparseable("negated answer")
            skipped_words = True
        if skipped_words and self.peek() is not None and self.peek().kind == "op" and self.peek().text in ("=", ":"):
            self.take()
        items = [self.parse_item()]
        has_or = False
        while self.peek() is not None:
            save = self.i
            is_or = False
            consumed = False
            while self.peek() is not None and (self.is_op(",") or self.is_op(";") or self.peek().kind == "conn"):
                tok = self.take()
                consumed = True
                is_or = is_or or (tok.kind == "conn" and tok.text == "or")
            if consumed and self.starts_item():
                items.append(self.parse_item())
                has_or = has_or or is_or
                if len(items) > MAX_ITEMS:
                    raise Unparseable("too many items")
            else:
                self.i = save
                break
        tok = self.peek()
        if tok is not None:
            if tok.kind == "word" or (tok.kind == "op" and tok.text in (",", ";")):
                pass  # trailing words (units, explanation) are ignored
            elif tok.kind == "conn":
                pass
            else:
                raise Unparseable(f"unexpected {tok.text!r}")
        if len(items) == 1:
            return items[0]
        return ("seq", "list", items, has_or)

    def parse_item(self) -> tuple:
        first = self.parse_rel()
        if not self.is_op("cup"):
            return first
        parts = [first]
        while self.is_op("cup"):
            self.take()
            parts.append(self.parse_rel())
        return ("union", parts)

    def parse_rel(self) -> tuple:
        operands = [self.parse_sum()]
        if self.is_op("in") and operands[0][0] == "sym":  # x \in [2, 5): the set is the answer
            self.take()
            return self.parse_sum()
        ops = []
        while self.peek() is not None and self.peek().kind == "op" and self.peek().text in _REL_OPS:
            ops.append(self.take().text)
            operands.append(self.parse_sum())
        if not ops:
            return operands[0]
        return ("rel", ops, operands)

    def parse_sum(self) -> tuple:
        terms = [(1, self.parse_unary())]
        while self.peek() is not None and self.peek().kind == "op" and self.peek().text in ("+", "-", "pm", "mp"):
            op = self.take().text
            sign = {"+": 1, "-": -1, "pm": "pm", "mp": "mp"}[op]
            terms.append((sign, self.parse_term()))
        if len(terms) == 1:
            return terms[0][1]
        return ("add", terms)

    def parse_unary(self) -> tuple:
        tok = self.peek()
        if tok is not None and tok.kind == "op":
            if tok.text == "-":
                self.take()
                return ("neg", self.parse_unary())
            if tok.text == "+":
                self.take()
                return self.parse_unary()
            if tok.text in ("pm", "mp"):
                self.take()
                return ("pm", self.parse_term())
        return self.parse_term()

    def parse_term(self) -> tuple:
        factors = [(self.parse_power(), 1)]
        while True:
            tok = self.peek()
            if tok is None:
                break
            if tok.kind == "op" and tok.text in ("*", "/"):
                self.take()
                factors.append((self.parse_signed_power(), 1 if tok.text == "*" else -1))
            elif tok.kind in _IMPLICIT_KINDS or (tok.kind == "op" and tok.text == "("):
                factors.append((self.parse_power(), 1))
            else:
                break
        if len(factors) == 1:
            return factors[0][0]
        return ("mul", factors)

    def parse_signed_power(self) -> tuple:
        if self.is_op("-"):
            self.take()
            return ("neg", self.parse_signed_power())
        if self.is_op("+"):
            self.take()
        return self.parse_power()

    def parse_power(self) -> tuple:
        base = self.parse_postfix()
        if self.is_op("^"):
            self.take()
            exp = self.parse_exponent()
            base = ("pow", base, exp)
            while self.is_op("%"):
                self.take()
                base = ("pct", base)
        return base

    def parse_exponent(self) -> tuple:
        if self.is_op("{"):
            return self.parse_group()
        if self.is_op("-"):
            self.take()
            return ("neg", self.parse_exponent())
        if self.is_op("+"):
            self.take()
        base = self.parse_primary()
        if self.is_op("^"):
            self.take()
            return ("pow", base, self.parse_exponent())
        return base

    def parse_postfix(self) -> tuple:
        node = self.parse_primary()
        while True:
            if self.is_op("!"):
                self.take()
                node = ("fact", node)
            elif self.is_op("%"):
                self.take()
                node = ("pct", node)
            else:
                return node

    def parse_group(self) -> tuple:
        """A LaTeX argument: {expr} or a single token."""
        if self.is_op("{"):
            self.take()
            node = self.parse_sum_or_rel()
            self.expect("}")
            return node
        tok = self.peek()
        if tok is not None and tok.kind == "num" and len(tok.text) > 1 and tok.text.isdigit():
            # \frac 12 style single-character argument
            self.t[self.i] = _Tok("num", tok.text[1:])
            return ("num", tok.text[0])
        return self.parse_primary()

    def parse_sum_or_rel(self) -> tuple:
        return self.parse_rel()

    def parse_bracketed(self, opener: str) -> tuple:
        closers = {"(": (")", "]"), "[": ("]", ")"), "{": ("}",), "\\{": ("\\}",)}[opener]
        items = []
        if self.peek() is not None and self.peek().kind == "op" and self.peek().text in closers:
            close = self.take().text
            if opener in ("{", "\\{"):
                return ("seq", "set", [], False)
            raise Unparseable("empty brackets")
        items.append(self.parse_item())
        while self.is_op(",") or self.is_op(";"):
            self.take()
            items.append(self.parse_item())
            if len(items) > MAX_ITEMS:
                raise Unparseable("too many items")
        tok = self.take()
        if tok.kind != "op" or tok.text not in closers:
            raise Unparseable(f"unclosed {opener!r}")
        close = tok.text
        if opener == "\\{":
            return ("seq", "set", items, False)
        if opener == "{":
            return items[0] if len(items) == 1 else ("seq", "set", items, False)
        if len(items) == 1:
            if opener == "(" and close == ")" or opener == "[" and close == "]":
                return items[0]
            raise Unparseable("half-open bracket around one value")
        if len(items) == 2:
            if opener == "(" and close == ")":
                return ("seq", "pair", items, False)
            return ("interval", items[0], items[1], opener == "(", close == ")")
        if close == ")" or (opener == "[" and close == "]"):
            return ("seq", "tuple", items, False)
        raise Unparseable("mismatched brackets")

    def parse_primary(self) -> tuple:
        tok = self.take()
        k, t = tok.kind, tok.text
        if k == "num":
            nxt, nxt2 = self.peek(), self.peek(1)
            if t.isdigit() and nxt is not None and nxt.kind == "cmd" and nxt.text == "frac" and nxt2 is not None:
                save = self.i
                self.take()
                a, b = self.parse_group(), self.parse_group()
                if a[0] == "num" and b[0] == "num" and a[1].isdigit() and b[1].isdigit():
                    return ("mixed", t, a[1], b[1])
                self.i = save
            return ("num", t)
        if k == "sym":
            name = t
            if self.is_op("_"):
                self.take()
                name += "_" + self.subscript_text()
            return ("sym", name)
        if k == "const":
            return ("const", t)
        if k == "empty":
            return ("seq", "set", [], False)
        if k == "func":
            return self.parse_function(t)
        if k == "cmd":
            if t == "frac":
                a = self.parse_group()
                b = self.parse_group()
                return ("mul", [(a, 1), (b, -1)])
            if t == "sqrt":
                n = None
                if self.is_op("["):
                    self.take()
                    n = self.parse_sum()
                    self.expect("]")
                arg = self.parse_group()
                return ("root", arg, n) if n is not None else ("func", "sqrt", arg, None)
            if t == "binom":
                return ("binom", self.parse_group(), self.parse_group())
        if k == "op":
            if t in ("(", "[", "{", "\\{"):
                return self.parse_bracketed(t)
            if t == "|":
                inner = self.parse_sum()
                self.expect("|")
                return ("abs", inner)
        if k == "word" and self.numeric_mode:
            raise Unparseable(f"unexpected word {t!r}")
        raise Unparseable(f"unexpected {t!r}")

    def subscript_text(self) -> str:
        if self.is_op("{"):
            self.take()
            parts = []
            while not self.is_op("}"):
                parts.append(self.take().text)
                if len(parts) > 20:
                    raise Unparseable("subscript too long")
            self.take()
            return "".join(parts)
        return self.take().text

    def parse_function(self, name: str) -> tuple:
        base = None
        power = None
        if self.is_op("_"):
            self.take()
            base = self.parse_group()
        if self.is_op("^"):
            self.take()
            power = self.parse_exponent()
        if self.is_op("("):
            self.take()
            arg = self.parse_rel()
            self.expect(")")
        elif self.is_op("{"):
            arg = self.parse_group()
        else:
            arg = self.parse_power()
        node = ("func", name, arg, base)
        if power is not None:
            node = ("pow", node, power)
        return node


def parse_answer_text(s: str, numeric_mode: bool = False) -> tuple:
    toks = tokenize(s, numeric_mode=numeric_mode)
    if not toks:
        raise Unparseable("empty answer")
    return _Parser(toks, numeric_mode).parse_answer()
