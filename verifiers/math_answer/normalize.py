"""Normalisation: LaTeX / unicode / percent / thousands clean-up, then our own tokenizer and
parser (no `eval`) that turns an answer into node tuples; trailing units and words are dropped
there. Policy: "Normalisation" in the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from posttrain.verifiers.math_answer.extract import _match_brace
from posttrain.verifiers.math_answer.guards import MAX_ITEMS, Unparseable


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


# --------------------------------------------------------------------------------------
# Repeating decimals: 1.\overline{45}, 0.\dot{3}, 0.1\dot{4}2\dot{8}, 0.(3), 0.333...
# --------------------------------------------------------------------------------------

_REPEAT_BAR_RE = re.compile(r"(?<![\d.])(\d*)\.(\d*)\s*\\(?:overline|bar|overbrace)\s*(?:\{\s*(\d+)\s*\}|(\d))")
_REPEAT_DOTS_RE = re.compile(r"(?<![\d.])(\d*)\.(\d*)\s*\\dot\s*\{?\s*(\d)\s*\}?(?:(\d*)\s*\\dot\s*\{?\s*(\d)\s*\}?)?")
_REPEAT_PAREN_RE = re.compile(r"(?<![\d.])(\d+)\.(\d*)\((\d+)\)")
_ELLIPSIS_RE = re.compile(r"(?<![\d.])(\d+)\.(\d+)\s*(?:\.{3}|\\[lc]?dots(?![A-Za-z]))")


def _repeating_value(whole: str, fixed: str, block: str) -> str:
    """whole.fixed(block)(block)... as an exact fraction, "(p/q)" (an integer when q is 1)."""
    from fractions import Fraction

    if len(fixed) + len(block) > 40:
        raise Unparseable("repeating decimal too long")
    value = Fraction(int(whole or "0")) + Fraction(int(fixed + block) - int(fixed or "0"),
                                                   10 ** len(fixed) * (10 ** len(block) - 1))
    return str(value.numerator) if value.denominator == 1 else f"({value.numerator}/{value.denominator})"


def _ellipsis(m: re.Match) -> str:
    whole, digits = m.group(1), m.group(2)
    for size in range(1, 7):  # the shortest block repeated at the end: 0.333..., 0.1666..., 0.4545...
        block = digits[-size:]
        if len(block) < size:
            break
        reps = 0
        while digits.endswith(block * (reps + 1)):
            reps += 1
        if reps >= 2:
            return _repeating_value(whole, digits[: len(digits) - size * reps], block)
    return f"{whole}.{digits}"  # no repetition: a truncated decimal, read as written


def _repeating_decimals(s: str) -> str:
    if "\\" in s:
        s = _REPEAT_BAR_RE.sub(lambda m: _repeating_value(m.group(1), m.group(2), m.group(3) or m.group(4)), s)
        s = _REPEAT_DOTS_RE.sub(lambda m: _repeating_value(
            m.group(1), m.group(2), m.group(3) + (m.group(4) or "") + (m.group(5) or "")), s)
    if "(" in s:
        s = _REPEAT_PAREN_RE.sub(lambda m: _repeating_value(m.group(1), m.group(2), m.group(3)), s)
    if "..." in s or "dots" in s:
        s = _ELLIPSIS_RE.sub(_ellipsis, s)
    return s


# --------------------------------------------------------------------------------------
# Matrices: \begin{pmatrix} a & b \\ c & d \end{pmatrix} -> \matbegin a & b \matrow c & d \matend
# --------------------------------------------------------------------------------------

_MAT_ENVS = r"(?:pmatrix|bmatrix|Bmatrix|vmatrix|Vmatrix|matrix|smallmatrix|array)"
_MAT_BEGIN_RE = re.compile(r"\\begin\s*\{\s*(" + _MAT_ENVS + r")\s*\}")
_MAT_END_RE = re.compile(r"\\end\s*\{\s*" + _MAT_ENVS + r"\s*\}")


def _matrices(s: str) -> str:
    if not _MAT_BEGIN_RE.search(s):
        return s

    def begin(m: re.Match) -> str:
        env = m.group(1)
        if env in ("vmatrix", "Vmatrix"):
            return " \\detbegin "
        return " \\matbegin "

    s = re.sub(r"\\begin\s*\{\s*array\s*\}\s*\{[^{}]*\}", r"\\begin{array}", s)  # drop the column spec
    s = _MAT_BEGIN_RE.sub(begin, s)
    s = _MAT_END_RE.sub(lambda m: " \\matend ", s)
    s = re.sub(r"\\hline(?![A-Za-z])", " ", s)
    return re.sub(r"\\\\(?:\s*\[[^\]]{0,10}\])?|\\cr(?![A-Za-z])", lambda m: " \\matrow ", s)


# --------------------------------------------------------------------------------------
# Number words: "nine", "forty-two", "two thousand", "one hundred and five", "two thirds"
# --------------------------------------------------------------------------------------

_NW_UNITS = {"zero": 0, "one": 1, "two": 2, "three": 3, "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8,
             "nine": 9, "ten": 10, "eleven": 11, "twelve": 12, "thirteen": 13, "fourteen": 14, "fifteen": 15,
             "sixteen": 16, "seventeen": 17, "eighteen": 18, "nineteen": 19}
_NW_TENS = {"twenty": 20, "thirty": 30, "forty": 40, "fifty": 50, "sixty": 60, "seventy": 70, "eighty": 80,
            "ninety": 90}
_NW_SCALES = {"hundred": 100, "thousand": 10 ** 3, "million": 10 ** 6, "billion": 10 ** 9, "trillion": 10 ** 12}
_NW_DENOMS = {"half": 2, "halves": 2, "third": 3, "thirds": 3, "quarter": 4, "quarters": 4, "fourth": 4,
              "fourths": 4, "fifth": 5, "fifths": 5, "sixth": 6, "sixths": 6, "seventh": 7, "sevenths": 7,
              "eighth": 8, "eighths": 8, "ninth": 9, "ninths": 9, "tenth": 10, "tenths": 10, "hundredth": 100,
              "hundredths": 100, "thousandth": 1000, "thousandths": 1000}
_NW_WORDS = set(_NW_UNITS) | set(_NW_TENS) | set(_NW_SCALES) | set(_NW_DENOMS)
_NW_ALT = "|".join(sorted(_NW_WORDS, key=len, reverse=True))
_NW_RUN_RE = re.compile(
    r"(?i)(?<![\w\\])(?:(?:minus|negative)\s+)?(?:an?\s+(?=(?:%s)\b))?(?:%s)"
    r"(?:(?:\s*-\s*|\s+(?:and\s+(?:an?\s+)?)?|\s+point\s+)(?:%s))*(?![\w])" % (
        "|".join(list(_NW_SCALES) + list(_NW_DENOMS)), _NW_ALT, _NW_ALT))
_DIGITS_SCALE_RE = re.compile(r"(?i)(?<![\w.])(\d+(?:\.\d+)?)\s+(hundred|thousand|million|billion|trillion)\b(?!\s+(?:and\b|\w+th))")
# "the two numbers", "each one", "no one": a number word after these is not the answer
_NW_BLOCKED_BEFORE = {"the", "these", "those", "all", "both", "each", "every", "first", "last", "next", "other",
                      "another", "any", "some", "which", "what", "whose", "no", "my", "our", "your", "their",
                      "his", "her", "its", "this", "that", "such", "same", "only"}
_NW_ONE_OK_BEFORE = {"is", "be", "equals", "equal", "exactly", "approximately", "about", "around", "roughly",
                     "just", "answer", "was", "are", "get", "gives", "makes", "minus", "negative", "plus", "to"}


def _nw_cardinal(words: list[str]) -> int | None:
    if not words:
        return None
    total, current, last, last_scale = 0, 0, None, None
    for k, w in enumerate(words):
        if w in ("a", "an"):
            if k != 0 or len(words) < 2 or words[1] not in _NW_SCALES:
                return None
            current, last = 1, "unit"
        elif w == "and":
            if last not in ("hundred", "scale") or k + 1 >= len(words) or words[k + 1] not in _NW_UNITS and words[k + 1] not in _NW_TENS:
                return None
        elif w in _NW_UNITS:
            v = _NW_UNITS[w]
            if last in ("unit", "teen") or (last == "tens" and not 0 < v < 10) or (v == 0 and len(words) > 1):
                return None
            current += v
            last = "teen" if v >= 10 else "unit"
        elif w in _NW_TENS:
            if last in ("unit", "teen", "tens"):
                return None
            current += _NW_TENS[w]
            last = "tens"
        elif w == "hundred":
            if last == "hundred" or current >= 100:
                return None
            current = (current or 1) * 100
            last = "hundred"
        elif w in _NW_SCALES:
            scale = _NW_SCALES[w]
            if last_scale is not None and scale >= last_scale:
                return None
            total += (current or (1 if k == 0 else 0)) * scale
            if k and not current:
                return None
            current, last, last_scale = 0, "scale", scale
        else:
            return None
    return total + current


def _nw_value(words: list[str]):
    """The value of a run of number words (int, Fraction, or a decimal string), or None."""
    from fractions import Fraction

    neg = bool(words) and words[0] in ("minus", "negative")
    if neg:
        words = words[1:]
    if not words:
        return None
    if "point" in words:
        i = words.index("point")
        whole = _nw_cardinal(words[:i]) if i else 0
        digits = words[i + 1:]
        if whole is None or not digits or any(d not in _NW_UNITS or _NW_UNITS[d] > 9 for d in digits):
            return None
        return ("-" if neg else "") + f"{whole}." + "".join(str(_NW_UNITS[d]) for d in digits)
    if words[-1] in _NW_DENOMS:
        den = _NW_DENOMS[words[-1]]
        head = words[:-1]
        whole = 0
        if "and" in head:
            j = len(head) - 1 - head[::-1].index("and")
            whole = _nw_cardinal(head[:j])
            head = head[j + 1:]
            if whole is None:
                return None
        if head in (["a"], ["an"]):
            num = 1
        else:
            num = _nw_cardinal(head)
            if num is None or num >= 100:
                return None
        if words[-1] in ("half", "halves") and num != 1 and not whole:
            return None  # "two halves" is not an answer
        value = whole + Fraction(num, den)
        return -value if neg else value
    value = _nw_cardinal(words)
    if value is None:
        return None
    return -value if neg else value


def _fmt_number(value) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, int):
        return str(value)
    if value.denominator == 1:
        return str(value.numerator)
    return f"({value.numerator}/{value.denominator})"


def _number_words(s: str) -> str:
    """Replace number words by digits where they state a number (see "Number words" in the docstring)."""
    low = s.lower()
    if not any(w in _NW_WORDS for w in re.findall(r"[a-z]+", low)):
        return s
    s = _DIGITS_SCALE_RE.sub(lambda m: _fmt_number(_scaled(m.group(1), m.group(2))), s)
    out, pos = [], 0
    for m in _NW_RUN_RE.finditer(s):
        words = re.findall(r"[a-z]+", m.group(0).lower())
        value = _nw_value(words)
        if value is None or not _nw_allowed(s, m.start(), m.end(), words):
            continue
        out.append(s[pos:m.start()])
        out.append(" " + _fmt_number(value) + " ")
        pos = m.end()
    out.append(s[pos:])
    return "".join(out)


def _scaled(digits: str, scale: str):
    from fractions import Fraction

    value = Fraction(digits) * _NW_SCALES[scale.lower()]
    return int(value) if value.denominator == 1 else value


def _nw_allowed(s: str, start: int, end: int, words: list[str]) -> bool:
    before = re.search(r"([A-Za-z']+|\S)\s*$", s[:start])
    prev = before.group(1).lower() if before else None
    after = re.match(r"\s*([A-Za-z']+)", s[end:])
    nxt = after.group(1).lower() if after else None
    if nxt in ("of", "another"):
        return False  # "one of the roots", "two of them"
    if prev in _NW_BLOCKED_BEFORE:
        return False
    if words == ["one"]:  # mostly a pronoun ("the larger one"): only right after "is", "=", ... or first
        return prev is None or prev in _NW_ONE_OK_BEFORE or prev in ("=", ":", "(", "-", "+", ",")
    return True


_CHOOSE_RE = re.compile(r"\{([^{}]*)\\choose(?![A-Za-z])([^{}]*)\}")


def clean_answer(s: str, merge_thousands: bool = True) -> str:
    """Normalise the surface of an extracted answer (see the package docstring)."""
    s = _UNICODE_RE.sub(lambda m: _UNICODE[m.group(0)], s)
    s = s.replace("`", " ")
    if "\\" in s:
        s = _matrices(s)
        if "choose" in s:
            s = _CHOOSE_RE.sub(r"\\binom{\1}{\2}", s)
    s = _repeating_decimals(s)
    s = _unwrap_text_commands(s)
    s = _number_words(s)
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
    # a trailing "!" is a factorial here (prose "!" is dropped at extraction); markdown emphasis
    # ("*5*", "_5_") and quotes around the whole answer ("'seven'") are not part of it
    s = re.sub(r"[\s.,;:?*_]+$", "", s)
    s = re.sub(r"^[\s:,;*_]+", "", s)
    quoted = re.fullmatch(r"([\"'])(.+)\1", s)
    if quoted:
        s = re.sub(r"[\s.,;:?*_]+$", "", quoted.group(2)).strip()
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
    r"|(?P<op>\*\*|!!|<=|>=|!=|==|[-+*/^!%=<>(),;\[\]{}|_:&])"
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
    "matbegin": ("op", "matbegin"), "matend": ("op", "matend"), "matrow": ("op", "matrow"),
    "detbegin": ("op", "detbegin"), "lbrack": ("op", "["), "rbrack": ("op", "]"),
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
_ITEM_START_OPS = {"(", "[", "{", "\\{", "-", "+", "pm", "mp", "|", "matbegin", "detbegin"}
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
            elif (tok.kind in _IMPLICIT_KINDS or (tok.kind == "op" and tok.text == "(")
                  or (tok.kind == "num" and factors[-1][0][0] in ("fact", "fact2"))):  # 4!2! = 4! * 2!
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
        bang = False
        while True:
            if self.is_op("!") or self.is_op("!!"):
                if bang:
                    raise Unparseable("ambiguous run of '!'")
                bang = True
                node = ("fact" if self.take().text == "!" else "fact2", node)
            elif self.is_op("%"):
                self.take()
                bang = False
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
            if t == "matbegin":
                return self.parse_matrix()
            if t == "detbegin":
                raise Unparseable("a determinant (vmatrix) is not a value")
            if t == "|":
                inner = self.parse_sum()
                self.expect("|")
                return ("abs", inner)
        if k == "word" and self.numeric_mode:
            raise Unparseable(f"unexpected word {t!r}")
        raise Unparseable(f"unexpected {t!r}")

    def parse_matrix(self) -> tuple:
        """Rows of entries after \\matbegin: `a & b \\matrow c & d \\matend` (a trailing row break is allowed)."""
        rows: list[list[tuple]] = [[]]
        count = 0
        while True:
            tok = self.peek()
            if tok is None:
                raise Unparseable("unclosed matrix")
            if tok.kind == "op" and tok.text == "matend":
                self.take()
                break
            if tok.kind == "op" and tok.text == "matrow":
                self.take()
                rows.append([])
                continue
            rows[-1].append(self.parse_item())
            count += 1
            if count > MAX_ITEMS:
                raise Unparseable("matrix too large")
            if self.is_op("&"):
                self.take()
                if self.is_op("&") or self.is_op("matrow") or self.is_op("matend"):
                    raise Unparseable("empty matrix entry")
            elif not (self.is_op("matrow") or self.is_op("matend")):
                tok = self.peek()
                raise Unparseable(f"unexpected {tok.text!r} in a matrix" if tok else "unclosed matrix")
        rows = [r for r in rows if r]
        if not rows or any(len(r) != len(rows[0]) for r in rows):
            raise Unparseable("ragged or empty matrix")
        return ("matrix", rows)

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
