"""Answer extraction: which part of a completion is the answer.

The policy (scope, rule order, last statement, connectives, retractions) is "Extraction policy"
and "Retractions" in the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from posttrain.verifiers.math_answer.guards import MAX_ITEMS


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
    math: bool = False  # the value is LaTeX math (a box or a math segment), not prose


_BOXED_RE = re.compile(r"\\(?:boxed|fbox)\s*\{")
_PHRASE_RE = re.compile(
    r"(?i)\b(?:final\s+answer|the\s+answer|answer)\b[\s*_]*"
    r"(?:(?P<neg>isn't|isn’t|is\s+not|is\s+n't)\s*[:：]?|is\b\s*[:：]?|[:：=]|would\s+be|will\s+be|should\s+be"
    r"|must\s+be|equals)[\s*_]*"
)
_HASHES_RE = re.compile(r"####[ \t]*([^\n]*)")
_RETRACT_RE = re.compile(
    r"(?i)(?:\bno,?\s+wait\b|\bwait,?\s+no\b"
    r"|\b(?:that|this)(?:'s|’s|\s+is|\s+was)\s+(?:wrong|incorrect|not\s+(?:right|correct))"
    r"|\bi\s+(?:have\s+)?made\s+(?:a|an)\s+(?:mistake|error)|\bi\s+was\s+wrong"
    r"|\bscratch\s+that|\blet\s+me\s+correct|\bcorrection\s*:|\bon\s+second\s+thought"
    r"|\bactually,?\s+no\b)"
)
# "it isn't 8", "that's not 8", "the answer is not 8", "8 is wrong": a retraction when it names the answer
_NEG_RESTATE_RE = re.compile(
    r"(?i)\b(?:it|that|this|the\s+(?:final\s+)?answer|the\s+result|my\s+answer)\s*"
    r"(?:isn't|isn’t|is\s+not|is\s+n't|'s\s+not|’s\s+not|wasn't|wasn’t|was\s+not|can't\s+be|can’t\s+be"
    r"|cannot\s+be|can\s+not\s+be|shouldn't\s+be|should\s+not\s+be)\s+(?:actually\s+|really\s+|equal\s+to\s+)?"
    r"(?P<val>[^;,\n]{1,80}?)\s*(?=[;,\n]|\.(?:\s|$)|$|\s+(?:but|since|because|rather)\b)"
)
# "\boxed{8}. No, it's 9." / "Wait, actually the answer is 9": a correction that states a new value right away
_CORRECTION_RE = re.compile(
    r"(?i)\b(?:no|wait|actually|oops|sorry|hmm,?\s+no|i\s+mean)\b[,.!]?\s+(?:(?:actually|wait|no),?\s+)?"
    r"(?:it(?:'s|’s|\s+is)|that(?:'s|’s|\s+is|\s+should\s+be)|the\s+(?:correct\s+|right\s+|final\s+)?answer\s+is"
    r"|make\s+that)\s+(?=[-−$\\(]|\d)"
)
# "option 8 is wrong" is about something else, not a retraction of the answer 8
_NAMED_ITEM_RE = re.compile(r"(?i)\b(?:option|choice|case|step|equation|line|part|statement|claim|item|method"
                            r"|approach|row|column|figure|page|number|no\.)\s*[(#]?\s*$")
_WRONG_RE = re.compile(r"(?i)\b(?:is|was)\s+(?:wrong|incorrect|not\s+(?:right|correct))\b")
# a value that starts by negating something: "not 8; it's 9", "it isn't 8, but 9"
_NEG_LEAD_RE = re.compile(
    r"(?i)^[\s*_]*(?:(?:it|that|this)\s*(?:is|was|'s|’s)?\s*)?(?:not|isn't|isn’t|wasn't|wasn’t|n't)\b\s*"
)
_NEG_ITEM_END_RE = re.compile(r"(?i)[;,]|\.(?=\s|$)|\s(?:but|rather|instead)\b|\n")
# a number right after a negation is not a candidate answer: "it's 9, not 8"
_NEGATED_BEFORE_RE = re.compile(
    r"(?i)(?:\bnot|n't|n’t|\bnever|\brather\s+than|\binstead\s+of|\bother\s+than)\s+"
    r"(?:be\s+|equal\s+to\s+|equals?\s+|exactly\s+)?\$?$"
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
    r"|(?P<num>(?<![\w.^])(?<!\^\{)-?(?:\d{1,3}(?:,\d{3})+(?![\d])|\d{1,3}(?:[ \u00a0\u202f\u2009]\d{3})+(?![\d])|\d+)"
    r"(?:\.\d+)?(?:[eE][-+]?\d+)?(?:!{1,2}(?![!=]))?"
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
    for o in outer:
        o.math = True
    return outer


# --------------------------------------------------------------------------------------
# "!" in prose: factorial or punctuation (policy: "Factorials" in the package docstring)
# --------------------------------------------------------------------------------------

_MATH_SEG_RE = re.compile(r"\$\$.*?\$\$|\\\[.*?\\\]|\\\(.*?\\\)|(?<![\\$])\$(?:\\\$|[^$])*?(?<!\\)\$", re.S)
_BANG_RUN_RE = re.compile(r"(?<!\\)!+")
_CURRENCY_BEFORE_RE = re.compile(r"(?:\\\$|\$|€|£|¥)\s*[\d,. ]*$")


_PAREN_NEGATION_RE = re.compile(r"(?i)\s*\(\s*(?:but\s+|and\s+)?(?:not|rather\s+than|instead\s+of)\b[^()]{0,60}\)")


def _prose_bangs(value: str) -> str:
    """Drop the "!" that are punctuation in a prose answer; keep factorials (and "!=").

    Also drops a parenthetical negation ("5 (not 6)"): it offers no value.

    Outside math segments a run of one or two "!" is a factorial only when it follows a digit
    or a closing bracket directly (no space) and the number is not a currency amount; any
    other "!" (after a word, a space, a "$", three or more in a row) ends a sentence.
    """
    if "(" in value and _PAREN_NEGATION_RE.search(value):
        value = _PAREN_NEGATION_RE.sub("", value)
    if "!" not in value:
        return value
    out = []
    pos = 0
    for m in _MATH_SEG_RE.finditer(value):
        out.append(_bangs_in_prose(value[pos:m.start()]))
        out.append(m.group(0))
        pos = m.end()
    out.append(_bangs_in_prose(value[pos:]))
    return "".join(out)


def _bangs_in_prose(chunk: str) -> str:
    if "!" not in chunk:
        return chunk

    def repl(m: re.Match) -> str:
        run, i = m.group(0), m.start()
        if chunk[m.end():m.end() + 1] == "=" and len(run) == 1:
            return run  # "x != 3"
        prev = chunk[i - 1] if i else ""
        if len(run) <= 2 and prev and (prev.isdigit() or prev in ")]}|") and not (
                prev.isdigit() and _CURRENCY_BEFORE_RE.search(chunk, max(0, i - 40), i)):
            return run
        return " "

    return _BANG_RUN_RE.sub(repl, chunk)


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
    for m in _SENTENCE_END_RE.finditer(line):
        if m.group(0) == "..." and _DECIMAL_BEFORE_RE.search(line, 0, m.start()):
            continue  # "0.333...": a repeating decimal, not the end of the sentence
        line = line[: m.start()]
        break
    return line, start + len(line)


_SENTENCE_END_RE = re.compile(r"\.\.\.(?=\s|$)|\.(?=\s|$)|\bI hope\b")
_DECIMAL_BEFORE_RE = re.compile(r"\d\.\d+$")


def _find_phrases(s: str) -> list[_Occ]:
    matches = list(_PHRASE_RE.finditer(s))
    occs: list[_Occ] = []
    for k, m in enumerate(matches):
        value, end = _sentence_value(s, m.end())
        if m.group("neg"):  # "the answer isn't 8; it's 9": a negated value (see _negated_lead)
            value = "not " + value
        if k + 1 < len(matches) and matches[k + 1].start() < end:
            cut = matches[k + 1].start() - m.end()
            value, end = value[:max(cut, 0)], matches[k + 1].start()
        stripped = re.sub(r"(?i)[\s,;]*\b(?:or|and)?[\s,;]*$", "", value)
        if not re.search(r"[\w\\]", stripped) or stripped.strip().lower() in {"the", "that", "this"}:
            continue
        shift = 4 if m.group("neg") else 0
        occs.append(_Occ(m.start(), m.end() + len(stripped) - shift, stripped, m.end() - shift))
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
        before = s[max(0, m.start() - 30):m.start()]
        if ("n" in before or "N" in before) and _NEGATED_BEFORE_RE.search(before):
            continue  # "it's 9, not 8": 8 is not offered as the answer
        after = s[m.end():m.end() + 24]
        if ("wrong" in after or "incorrect" in after or " not " in after) and _WRONG_RE.match(after.lstrip()):
            continue  # "8 is wrong": not offered either
        if group == "num" and value.endswith("!") and _CURRENCY_BEFORE_RE.search(s, max(0, m.start() - 3), m.start()):
            value = value.rstrip("!")  # "$18!" is an amount, exclaimed
        occs.append(_Occ(offset + m.start(), offset + m.end(), value, offset + m.start(group),
                         math=group in ("dd", "db", "ip", "id", "tex")))
    exprs = _plain_expressions(s, offset, occs)
    if exprs:
        occs = [o for o in occs if not any(e.start <= o.start and o.end <= e.end for e in exprs)] + exprs
        occs.sort(key=lambda o: o.start)
    return occs


# An algebraic expression written in plain text ("factors as (a-2)^2"): single-letter variables,
# numbers, + - * / ^ and brackets, no words. Numbers inside it are not candidates of their own.
_PLAIN_ATOM = (r"(?:(?<![A-Za-z'’])[A-Za-z](?![A-Za-z'’])|(?<![A-Za-z])(?:sqrt|sin|cos|tan|log|ln|exp)(?=\s*\()"
               r"|\d+(?:\.\d+)?|[-+*/^()])")
_PLAIN_RUN_RE = re.compile(r"(?<![\w\\$'’{^])" + _PLAIN_ATOM + r"(?:[ \t]*" + _PLAIN_ATOM + r")*")
_PLAIN_SHAPE_RE = re.compile(r"[-+*/^]|\d\s*[A-Za-z(]|\)\s*[(A-Za-z\d]")


def _plain_expressions(s: str, offset: int, occs: list[_Occ]) -> list[_Occ]:
    if not any(c in s for c in "+-*/^"):
        return []
    math_spans = [(o.start - offset, o.end - offset) for o in occs if o.math]
    out = []
    for m in _PLAIN_RUN_RE.finditer(s):
        text = m.group(0)
        if len(text) < 3 or not any(c.isalpha() for c in text):
            continue
        start, end = m.start(), m.end()
        # trim markdown stars, trailing operators and a leading article / pronoun ("a (x+1)" is prose)
        while text and text[-1] in "-+*/^ ":
            text, end = text[:-1], end - 1
        while text and text[0] in "*+/^ ":
            text, start = text[1:], start + 1
        lead = re.match(r"(?:[aAI]\s+)(?=[(\d])", text)
        if lead:
            text, start = text[lead.end():], start + lead.end()
        if (len(text) < 3 or not any(c.isalpha() for c in text) or not _PLAIN_SHAPE_RE.search(text)
                or text.count("(") != text.count(")") or _unbalanced(text)):
            continue
        if any(a < end and start < b for a, b in math_spans):
            continue
        out.append(_Occ(offset + start, offset + end, text, offset + start))
    return out


def _unbalanced(text: str) -> bool:
    depth = 0
    for c in text:
        depth += (c == "(") - (c == ")")
        if depth < 0:
            return True
    return depth != 0


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
        while len(occs) > 1 and not occs[-1].math and _NEG_LEAD_RE.match(occs[-1].value) and depth < 8 \
                and _after_negation(s, occs[-1], depth) is None:
            occs.pop()  # "the answer is not 3" offers nothing: an earlier statement stands (or is retracted)
        if occs:
            found = (rule, _last_group(occs, s))
            break
    if found is None:
        if in_tag:
            content = s.strip()
            if depth < 8 and _NEG_LEAD_RE.match(content):
                again = _after_negation(s, _Occ(0, len(s), content, 0), depth)
                if again is not None:
                    return again[0]
            return Extraction("answer tag", [_prose_bangs(content)], fallback_text=s)
        occs = _find_last_numbers(s)
        if not occs:
            return None
        found = ("last number", _last_group(occs, s))
    rule, group = found
    last = group[-1]
    if depth < 8 and not last.math and _NEG_LEAD_RE.match(last.value):
        # "the answer is not 8; it's 9": the negated value is withdrawn, what follows counts
        again = _after_negation(s, last, depth)
        if again is not None:
            return _retracted_or(s, again[1], again[0], depth)
    ext = Extraction(rule, [o.value if o.math else _prose_bangs(o.value) for o in group])
    return _retracted_or(s, last.end, ext, depth)


def _retracted_or(s: str, start: int, ext: Extraction, depth: int) -> Extraction:
    """ext, unless a retraction follows it after `start`: then the answer after the retraction."""
    end = _retraction(s, start, ext.parts)
    if end is not None and depth < 8:
        again = _extract_in(s[end:], in_tag=False, depth=depth + 1)
        if again is not None:
            return again
        ext.retracted = True
    return ext


def _after_negation(s: str, occ: _Occ, depth: int) -> tuple[Extraction, int] | None:
    """The answer stated after a negated value ("not 8; it's 9") and where it ends, or None."""
    value = occ.value
    lead = _NEG_LEAD_RE.match(value)
    end = _NEG_ITEM_END_RE.search(value, lead.end())
    if end is not None:
        again = _extract_in(value[end.start():], in_tag=False, depth=depth + 1)
        return None if again is None else (again, occ.end)
    # "The answer is not 8. It's 9.": the next sentence
    after = s[occ.end:occ.end + 400]
    m = re.match(r"\s*[.;,]?\s*(?:(?:it|that)(?:'s|’s|\s+is)|but|rather|instead)\b([^\n]*?)(?:\.(?=\s|$)|\n|$)", after, re.I)
    if m is None:
        return None
    again = _extract_in(m.group(1), in_tag=False, depth=depth + 1)
    return None if again is None else (again, occ.end + m.end())


def _norm_value(v: str) -> str:
    return re.sub(r"[\s$*{}]|\\[()\[\]]|\\text|[.!]+$", "", v).lower()


def _retraction(s: str, start: int, parts: list[str]) -> int | None:
    """Where a retraction of the answer just given ends (the text after it is read again), or None.

    A self-referential phrase (_RETRACT_RE) anywhere after the answer, or a negated restatement
    of the answer itself ("it isn't 8", "8 is wrong") - a negation of something else is not one.
    """
    found = []
    m = _RETRACT_RE.search(s, start)
    if m is not None:
        found.append(m.end())
    c = _CORRECTION_RE.search(s, start, start + 4000)
    if c is not None:
        found.append(c.end())
    wanted = {_norm_value(p) for p in parts}
    wanted.discard("")
    if wanted:
        window = s[start:start + 4000]
        for n in _NEG_RESTATE_RE.finditer(window):
            if _norm_value(n.group("val")) in wanted:
                found.append(start + n.end())
                break
        stated = {p.strip() for p in parts if p.strip()}
        for w in _WRONG_RE.finditer(window):  # "8 is wrong": the answer itself, right before
            before = window[:w.start()].rstrip()
            for pn in stated:
                k = len(before) - len(pn)
                if (before.endswith(pn) and (k == 0 or not before[k - 1].isalnum())
                        and not _NAMED_ITEM_RE.search(before, max(0, k - 30), k)):
                    found.append(start + w.end())
                    break
            else:
                continue
            break
    return min(found) if found else None


def extract_answer(text: str) -> Extraction | None:
    """Apply the extraction policy of the package docstring; None when no answer is stated."""
    scope, kind = _scope(text)
    if kind == "tag":
        after = text[text.lower().rfind("</answer>") + len("</answer>"):]
        ext = _extract_in(scope, in_tag=True)
        end = _retraction(after, 0, ext.parts if ext is not None else [])
        if end is not None:  # "<answer>5</answer> No wait, that's wrong: 6"
            again = _extract_in(after[end:], in_tag=False, depth=1)
            if again is not None:
                return again
            if ext is not None:
                ext.retracted = True
            return ext
        return ext
    if kind == "after_think":
        ext = _extract_in(scope, in_tag=False)
        if ext is not None:
            return ext
        return _extract_in(text, in_tag=False)
    return _extract_in(text, in_tag=False)
