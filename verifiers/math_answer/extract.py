"""Answer extraction: which part of a completion is the answer.

The policy (scope, rule order, last statement, connectives, retractions) is "Extraction policy"
and "Retractions" in the package docstring, verifiers/math_answer/__init__.py.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

from verifiers.math_answer.guards import MAX_ITEMS


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
    """Apply the extraction policy of the package docstring; None when no answer is stated."""
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
