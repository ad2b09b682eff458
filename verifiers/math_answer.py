"""Math answer verifier (registry name "math"): extract the final answer, normalise it, compare to the gold.

The reference is the gold answer: a string (`"3/4"`, `"\\frac{3}{4}"`, `"(1, 2]"`, `"x = 3"`,
`"\\{1, 2\\}"`, `"25\\%"`, `"\\text{Evelyn}"`) or a number. A reference we cannot parse is a
bug in the problem set and raises ValueError. The completion is scored 1.0 or 0.0 with a reason:
"correct", "wrong answer", "no answer found", "unparseable answer", "multiple answers",
"answer retracted", "unevaluated expression", "comparison budget exceeded". `details` holds
{"rule", "extracted", "normalized", "gold"} (and "error" for an unparseable answer).

Extraction policy (applied in this order; the first rule that finds something decides):

0. Scope. If the completion holds a closed `<answer>...</answer>` pair, only the content of the
   *last* pair is looked at (text after it is ignored, except a retraction: see below).
   Otherwise, if it holds `</think>`, the text after the last `</think>` is looked at first
   (falling back to the whole text when it yields nothing): tentative answers inside a
   reasoning block do not count.
1. `\\boxed{...}` / `\\fbox{...}` (balanced braces, nested braces and `\\{ \\}` handled).
2. An answer phrase: "the answer is ...", "final answer: ...", "answer: ...", "answer = ...",
   "the answer would/should/will/must be ...", "the answer equals ..." (case-insensitive, markdown
   `**` tolerated). The value runs
   to the end of the sentence (a "." followed by a space or the end) or of the line; an empty
   rest of line takes the next non-empty line.
3. `#### ...` (GSM8K style), to the end of the line.
4. Inside an `<answer>` scope only: the whole tag content.
5. The last number in the text: a bare number (sign, thousands separators, decimals, a/b,
   `1e3`, `2.9 \\times 10^{4}`, `2^{10}`, percent), a bare LaTeX run (`\\frac{a}{b}`, `7\\sqrt{5}`,
   `3\\pi`), or an inline/display math segment (`$...$`, `$$...$$`, `\\(...\\)`, `\\[...\\]`),
   whichever ends last (inside an `<answer>` scope, when the whole content does not parse).

Within a rule, the LAST occurrence counts, so "the answer is 5. Wait, actually the answer is 6"
gives 6. Exactly: occurrences of the winning rule are ordered by position and the last one is
taken, together with the occurrences just before it that are separated from it only by
connectives (whitespace, `,` `;` `/` `&`, "and", "or", "either", `\\text{ or }`, `\\quad`, math
delimiters): those form one statement that offers several values.

Retractions. After the chosen answer, a self-referential retraction ("no wait", "wait, no",
"that's wrong/incorrect/not right", "this is wrong", "I made a mistake", "I was wrong",
"scratch that", "let me correct", "correction:", "on second thought", "actually, no") voids it:
the answer is re-extracted from the text after the retraction with the same rules, and when
that text holds none the verdict is "answer retracted". Third-person phrases ("option C is
wrong") are not retractions.

Several candidate answers (reward-hack guard). A statement that offers several *different*
values when the gold is a single value scores 0 with reason "multiple answers": adjacent
boxes (`\\boxed{3} or \\boxed{4}`), lists (`the answer is 3, 4, 5 or 6`), `\\pm` (`\\pm 3` is
{3, -3}). When the gold itself has several elements (a set, a list of roots), such a statement
is read as a set and compared to the gold set. Only one statement ever counts, so spreading
guesses over several statements ("\\boxed{3}. Hmm, maybe \\boxed{4}") earns nothing either: the
last one is the answer.

Normalisation: math delimiters (`$`, `$$`, `\\(`, `\\)`, `\\[`, `\\]`), `\\left`/`\\right`,
`\\displaystyle`, `\\text{}`/`\\mathrm{}`/`\\textbf{}`/`\\mbox{}` (content kept), `\\dfrac`/`\\tfrac`/
`\\cfrac` (= `\\frac`, also `\\frac12`), `\\sqrt{}`/`\\sqrt[n]{}`/`\\sqrt2`, `\\pi`, `\\cdot`, `\\times`,
`\\div`, `\\infty`, degrees (`^\\circ`), markdown bold, unicode (minus signs, `×`, `÷`, `√`, `π`,
`∞`, `≤`, `≥`, `±`, superscripts, vulgar fractions), percentages (`%`, `\\%`, "percent"),
thousands separators (`1,234,567`, `1{,}234`, `1\\,234`, `1 234`; never inside a tuple when the
gold is a tuple/set, and "1,2" is always a list), scientific notation (`1e3`, `1.5 \\times 10^{3}`),
mixed numbers (`2\\frac{1}{2}` = 5/2), leading words ("approximately 5", "I think it's 5") and trailing units
or words ("5 apples", "$5", "5 cm", "5 m/s"; a single letter is read as a unit only when the gold
has no variables and the letter is not x, y, z, n or k). A leading negation ("not 5") makes the
answer unparseable. A trailing "!" is punctuation, not a factorial.

Equivalence: exact rationals (0.5 == 1/2 == 50%); a relative tolerance `rel_tol` (default 1e-6)
applies only when one side is inexact (written with decimals or scientific notation), so
1000000 != 1000001 while 0.3333333 == 1/3; exact irrational forms must agree to 20 digits.
Symbolic answers are equal when sympy proves `a - b == 0` (expand/cancel/simplify) or the
difference vanishes at 5 seeded random points at 40-digit precision (a probabilistic identity
test); all sympy work runs under a budget counted in Python function calls
(`symbolic_budget`, default 1e6 calls, well under a second), so a pathological expression ends
as "comparison budget exceeded" instead of a hang (deterministic up to sympy's internal caches,
which only make a repeated comparison cheaper). Sets (`\\{1,2\\}`, bare lists "1, 2") are order-insensitive; tuples `(1, 2, 3)` are
ordered; `(a, b)` is both a pair and an open interval; intervals `(1, 2]`, `[0, \\infty)` and unions
`\\cup` compare endpoints and openness; one-variable inequalities (`x > 3`, `1 < x \\le 2`) are read
as intervals. Equations: `x = 3` vs `3` compares the right-hand side (the last one of a chain
`a = b = 5`); two general equations are equal when `lhs - rhs` agree up to a non-zero constant
factor. A singleton set equals its element. Text answers (`\\text{Evelyn}`) compare
case-insensitively after removing spaces and punctuation.

Percent: when exactly one side is written with a percent sign, p% matches p or p/100 on the
other side (gold "25%" accepts 25, 0.25, 1/4); when both are, the numbers must match.

Unevaluated arithmetic: when the gold is a plain rational number (integer, decimal, fraction),
a prediction with a rational value must be written as a number literal too (integer, decimal,
a/b, \\frac{a}{b}, mixed number, m x 10^k, with an optional percent sign):
`\\boxed{123 \\times 456}` for 56088 is "unevaluated expression" (score 0), because RL on
arithmetic otherwise learns to restate the question. Irrational forms (`\\pi` for 3.14159265)
are compared numerically. Set `allow_unevaluated=True` to accept arithmetic.

Hard limits on model output (checked before any sympy work): an extracted answer over 1000
characters, a power over 4000 digits (`9^{9^{9^9}}`), a factorial over 3000!, more than 64
list items or 4 `\\pm` signs is "unparseable answer". The verifier never evaluates model text
with `eval`: answers go through our own tokenizer and parser and are built into sympy objects
directly. The runner (verifiers/runner.py) adds the wall-clock limit around all of this.

huggingface/Math-Verify is the reference we compared against. Where we agree: `\\boxed` first
then answer phrases then plain numbers/LaTeX, rightmost match wins within a priority, thousands
separators, `\\frac13`/`\\sqrt3`, `\\text{}` units, `k = 1/3` counts as 1/3, percent handling,
adjacent answers joined by and/or/commas form a set, intervals are open/closed sensitive.
Where we deliberately differ (and why):
- Math-Verify reads `$3$ or $4$` as the set {3, 4}, and its verify() succeeds when any parsed
  candidate matches; we refuse a multi-valued statement against a single-valued gold
  ("multiple answers"), because accepting it rewards hedging.
- Math-Verify accepts `\\pm 2021` for 2021 (its issue #14); we read `\\pm` as two values.
- Math-Verify rounds floats to 6 decimals and so equates 1/2004! and 1/2006! (issue #14); we use
  a relative tolerance and only when a side is inexact.
- Math-Verify's timeout uses signal.alarm (main thread only); we use a deterministic call budget
  inside and the runner's worker processes outside, so scoring works from any thread.
- We honour `<answer>` tags and `</think>` as scopes, and retractions after the answer.
- We reject unevaluated arithmetic for a plain-number gold (see above); Math-Verify accepts it.
- We do not read a decimal comma ("1,5" is the list 1, 5, not 1.5), matrices, or number words
  ("five"); such answers are "unparseable answer" or compared as text.
"""
from __future__ import annotations

import math
import random
import re
import sys
import threading
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache
from typing import Any

from verifiers.base import AuditProblem, Verdict, Verifier

MAX_ANSWER_CHARS = 1000   # longest extracted answer we try to parse
MAX_DIGITS = 4000         # largest number we build (also below Python's int->str limit)
MAX_FACTORIAL = 3000
MAX_ITEMS = 64            # list / set / tuple elements
MAX_PM = 4                # \pm signs in one answer (2**4 alternatives)
DEFAULT_BUDGET = 1_000_000  # Python function calls for all sympy work on one completion

_sympy = None


def _sp():
    """sympy, imported on first use (numeric answers never need it)."""
    global _sympy
    if _sympy is None:
        import sympy

        _sympy = sympy
    return _sympy


class Unparseable(Exception):
    """The model's answer cannot be read (bad model output, never raised out of `check`)."""


class _BudgetExceeded(BaseException):
    """Raised from the call tracer; BaseException so sympy's `except Exception` cannot swallow it."""


_budget_state = threading.local()


class _CallBudget:
    """Limit the Python function calls made inside a block (deterministic, thread-local).

    Implemented with `sys.settrace`: the global trace function counts 'call' events and raises
    `_BudgetExceeded` past the limit. Works in any thread and in worker processes. It cannot
    interrupt a single long C call, which is why big numbers are refused before they are built.
    """

    def __init__(self, limit: int):
        self.limit = limit
        self.nested = False

    def __enter__(self) -> "_CallBudget":
        if getattr(_budget_state, "active", False):
            self.nested = True
            return self
        _budget_state.active = True
        self._old = sys.gettrace()
        count = 0
        limit = self.limit

        def tracer(frame, event, arg):
            nonlocal count
            count += 1
            if count > limit:
                raise _BudgetExceeded()
            return None

        sys.settrace(tracer)
        return self

    def __exit__(self, *exc) -> None:
        if self.nested:
            return
        sys.settrace(self._old)
        _budget_state.active = False


# --------------------------------------------------------------------------------------
# Extraction
# --------------------------------------------------------------------------------------


@dataclass
class Extraction:
    """What the extraction rules found: one statement (several parts when it offers several values)."""

    rule: str
    parts: list[str]
    retracted: bool = False
    fallback_text: str | None = None  # for "answer tag": where to look for a last number


@dataclass
class _Occ:
    start: int  # where the marker starts (\boxed, "the answer is", ...)
    end: int  # where the value ends
    value: str
    value_start: int


_BOXED_RE = re.compile(r"\\(?:boxed|fbox)\s*\{")
_PHRASE_RE = re.compile(
    r"(?i)\b(?:final\s+answer|the\s+answer|answer)\b[\s*_]*"
    r"(?:is\s*[:：]?|[:：=]|would\s+be|will\s+be|should\s+be|must\s+be|equals)[\s*_]*"
)
_HASHES_RE = re.compile(r"####[ \t]*([^\n]*)")
_RETRACT_RE = re.compile(
    r"(?i)(?:\bno,?\s+wait\b|\bwait,?\s+no\b"
    r"|\b(?:that|this)(?:'s|’s|\s+is|\s+was)\s+(?:wrong|incorrect|not\s+(?:right|correct))"
    r"|\bi\s+(?:have\s+)?made\s+(?:a|an)\s+(?:mistake|error)|\bi\s+was\s+wrong"
    r"|\bscratch\s+that|\blet\s+me\s+correct|\bcorrection\s*:|\bon\s+second\s+thought"
    r"|\bactually,?\s+no\b)"
)
_CONNECTIVE_GAP_RE = re.compile(
    r"(?:\s|[,;/&$*]|\\[()\[\]]|\\(?:quad|qquad|lor|vee|,|;)"
    r"|\\text\s*\{\s*(?:or|and|,)?\s*\}|\b(?:or|and|either)\b)*",
    re.I,
)
_LAST_RE = re.compile(
    r"\$\$(?P<dd>[^$]{1,2000}?)\$\$"
    r"|\\\[(?P<db>.{1,2000}?)\\\]"
    r"|\\\((?P<ip>.{1,2000}?)\\\)"
    r"|(?<![\\$\w])\$(?P<id>(?:\\\$|[^$\n]){1,1000}?)(?<!\\)\$(?!\d)"
    r"|(?P<tex>-?(?:\d+(?:\.\d+)?)?(?:\\(?:sqrt|[dtc]?frac|pi)(?![A-Za-z])(?:\[[^\]]{1,20}\])?"
    r"(?:\{[^{}]{1,100}\}|\d){0,2})+(?:\^\{?-?\d+\}?)?)"
    r"|(?P<num>(?<![\w.])-?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:[eE][-+]?\d+)?"
    r"(?:\s*\^\s*\{?\s*-?\d+\s*\}?)?"
    r"(?:\s*(?:\\times|\\cdot|\*)\s*10\s*\^\s*\{?\s*-?\d+\s*\}?)?"
    r"(?:\s*/\s*\d+(?:\.\d+)?)?(?:\s*(?:\\?%|percent\b))?)",
    re.S,
)
_TAIL_WINDOW = 65536


def _match_brace(s: str, open_idx: int, cap: int = 20000) -> int | None:
    """Index of the '}' that closes the '{' at open_idx (escaped braces skipped), or None."""
    depth = 0
    end = min(len(s), open_idx + cap)
    i = open_idx
    while i < end:
        c = s[i]
        if c == "\\":
            i += 2
            continue
        if c == "{":
            depth += 1
        elif c == "}":
            depth -= 1
            if depth == 0:
                return i
        i += 1
    return None


def _find_boxed(s: str) -> list[_Occ]:
    starts = [m for m in _BOXED_RE.finditer(s)]
    occs: list[_Occ] = []
    for m in starts[-32:]:  # only the tail matters; bounds the work on adversarial input
        close = _match_brace(s, m.end() - 1)
        if close is None:
            continue
        occs.append(_Occ(m.start(), close + 1, s[m.end():close], m.end()))
    # a box nested in another box belongs to the outer one
    outer = [o for o in occs if not any(p is not o and p.start < o.start and o.end <= p.end for p in occs)]
    return outer


def _sentence_value(s: str, start: int) -> tuple[str, int]:
    """The value after an answer phrase: to the end of the sentence or line (at most 400 chars)."""
    rest = s[start:start + 400]
    nl = rest.find("\n")
    if nl >= 0 and not rest[:nl].strip():
        skipped = len(rest) - len(rest[nl:].lstrip())
        rest = rest[skipped:]
        start += skipped
        nl = rest.find("\n")
    if rest.startswith("$$") or rest.startswith("\\["):
        closer = "$$" if rest.startswith("$$") else "\\]"
        close = rest.find(closer, 2)
        if close >= 0:
            return rest[: close + 2], start + close + 2
    line = rest if nl < 0 else rest[:nl]
    m = re.search(r"\.(?=\s|$)|\bI hope\b", line)
    if m:
        line = line[: m.start()]
    return line, start + len(line)


def _find_phrases(s: str) -> list[_Occ]:
    matches = list(_PHRASE_RE.finditer(s))
    occs: list[_Occ] = []
    for k, m in enumerate(matches):
        value, end = _sentence_value(s, m.end())
        if k + 1 < len(matches) and matches[k + 1].start() < end:
            cut = matches[k + 1].start() - m.end()
            value, end = value[:max(cut, 0)], matches[k + 1].start()
        stripped = re.sub(r"(?i)[\s,;]*\b(?:or|and)?[\s,;]*$", "", value)
        if not re.search(r"[\w\\]", stripped) or stripped.strip().lower() in {"the", "that", "this"}:
            continue
        occs.append(_Occ(m.start(), m.end() + len(stripped), stripped, m.end()))
    return occs


def _find_hashes(s: str) -> list[_Occ]:
    return [_Occ(m.start(), m.end(1), m.group(1), m.start(1)) for m in _HASHES_RE.finditer(s) if m.group(1).strip()]


def _find_last_numbers(s: str) -> list[_Occ]:
    if len(s) > _TAIL_WINDOW:
        offset = len(s) - _TAIL_WINDOW
        occs = _scan_numbers(s[offset:], offset)
        if occs:
            return occs
    return _scan_numbers(s, 0)


def _scan_numbers(s: str, offset: int) -> list[_Occ]:
    occs = []
    for m in _LAST_RE.finditer(s):
        group = m.lastgroup
        value = m.group(group)
        occs.append(_Occ(offset + m.start(), offset + m.end(), value, offset + m.start(group)))
    return occs


def _last_group(occs: list[_Occ], s: str) -> list[_Occ]:
    """The last occurrence plus the ones before it joined only by connectives."""
    group = [occs[-1]]
    for prev in reversed(occs[:-1]):
        gap = s[prev.end:group[0].start]
        if prev.end <= group[0].start and _CONNECTIVE_GAP_RE.fullmatch(gap):
            group.insert(0, prev)
        else:
            break
    return group[-MAX_ITEMS:]


def _scope(text: str) -> tuple[str, str]:
    low = text.lower()
    close = low.rfind("</answer>")
    if close >= 0:
        open_ = low.rfind("<answer>", 0, close)
        if open_ >= 0 and text[open_ + 8:close].strip():
            return text[open_ + 8:close], "tag"
    think = low.rfind("</think>")
    if think >= 0:
        return text[think + 8:], "after_think"
    return text, "all"


def _extract_in(s: str, in_tag: bool, depth: int = 0) -> Extraction | None:
    found: tuple[str, list[_Occ]] | None = None
    for rule, finder in (("boxed", _find_boxed), ("answer phrase", _find_phrases), ("####", _find_hashes)):
        occs = finder(s)
        if occs:
            found = (rule, _last_group(occs, s))
            break
    if found is None:
        if in_tag:
            return Extraction("answer tag", [s.strip()], fallback_text=s)
        occs = _find_last_numbers(s)
        if not occs:
            return None
        found = ("last number", _last_group(occs, s))
    rule, group = found
    ext = Extraction(rule, [o.value for o in group])
    tail_start = group[-1].end
    m = _RETRACT_RE.search(s, tail_start)
    if m is not None and depth < 8:
        again = _extract_in(s[m.end():], in_tag=False, depth=depth + 1)
        if again is not None:
            return again
        ext.retracted = True
    return ext


def extract_answer(text: str) -> Extraction | None:
    """Apply the extraction policy of the module docstring; None when no answer is stated."""
    scope, kind = _scope(text)
    if kind == "tag":
        after = text[text.lower().rfind("</answer>") + len("</answer>"):]
        m = _RETRACT_RE.search(after)
        if m is not None:  # "<answer>5</answer> No wait, that's wrong: 6"
            again = _extract_in(after[m.end():], in_tag=False, depth=1)
            ext = _extract_in(scope, in_tag=True)
            if again is not None:
                return again
            if ext is not None:
                ext.retracted = True
            return ext
        return _extract_in(scope, in_tag=True)
    if kind == "after_think":
        ext = _extract_in(scope, in_tag=False)
        if ext is not None:
            return ext
        return _extract_in(text, in_tag=False)
    return _extract_in(text, in_tag=False)


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
    """Normalise the surface of an extracted answer (see the module docstring)."""
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


# --------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------


@dataclass
class Scalar:
    node: tuple
    frac: Fraction | None  # the value when it is rational and known without sympy
    inexact: bool  # written with decimals / scientific notation
    literal: bool  # a plain number literal (see module docstring)
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
    if kind == "fact":
        v = _frac_eval(node[1])
        if v is None or v[0].denominator != 1 or v[0] < 0:
            return None
        if v[0] > MAX_FACTORIAL:
            raise Unparseable("number too large")
        return Fraction(math.factorial(int(v[0]))), v[1]
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
        if pa == 1 and pb == -1:  # a/b, \frac{a}{b}
            a_inner = a[1] if a[0] == "neg" else a
            return _is_int_num(a_inner) and _is_int_num(b)
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
    fr = _frac_eval(node) if kind in ("num", "mixed", "neg", "add", "mul", "pow", "fact", "binom", "pct") else None
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
        return sp.root(_to_sympy(node[1]), n)
    if kind == "abs":
        return sp.Abs(_to_sympy(node[1]))
    if kind == "fact":
        v = _to_sympy(node[1])
        if v.is_Number and (not v.is_Integer or v > MAX_FACTORIAL):
            raise Unparseable("factorial out of range")
        return sp.factorial(v)
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
    if kind == "rel":
        _, ops, operands = node
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
    if not words or re.search(r"[\d\\^=+*/]", stripped):
        return False
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
            node = parse_answer_text(cleaned)
            value = build_value(node)
            if isinstance(value, (Seq, Interval, IntervalUnion)):
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
    sequence = isinstance(value, (Seq, Interval, IntervalUnion))
    return Gold(raw, value, numeric, sequence)


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
    """Final-answer math: extraction, LaTeX normalisation, sympy equivalence (see module docstring)."""

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
