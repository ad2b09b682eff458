"""Format and length helpers, meant to be composed with a correctness verifier (see combine.py).

FormatVerifier (registry name "format"): does the completion present its answer the required way?
- default: a non-empty `\\boxed{...}` (balanced braces) or a non-empty `<answer>...</answer>`;
- `tags="answer"` or `tags=("think", "answer")`: each tag present exactly once, non-empty,
  closed, and in the given order (a repeated tag is a failure: one answer per completion);
- `boxed=True`: a non-empty `\\boxed{...}` is required (with tags: in addition to them);
- `pattern=REGEX`: the regex must be found (`re.search`, DOTALL), or match the whole stripped
  completion with `full_match=True`; an invalid regex is a ValueError at construction.
Score 1.0 "ok" when every requirement holds, else 0.0 with the first failure as the reason
(`partial=True`: the fraction of requirements met). details: {"checks": {requirement: bool}}.

LengthVerifier (registry name "length"): 1.0 within a budget, then decaying linearly to 0.0 at
`budget + window` (window defaults to the budget: 0 at twice the budget). Counts characters
(`max_chars`, default 4000) or tokens (`max_tokens`): with `tokenizer=callable(str) -> int |
list` (e.g. a Hugging Face tokenizer's `encode`), else an approximation (words and punctuation
marks, regex `\\w+|[^\\w\\s]`). The reference is ignored.

Both are cheap and bounded (linear scans), so they run in the calling process
(`in_process = True`, still under the runner's wall-clock limit).
"""
from __future__ import annotations

import re
from typing import Any, Callable, Sequence

from posttrain.verifiers.base import Verdict, Verifier
from posttrain.verifiers.math_answer import _match_brace

_BOXED_RE = re.compile(r"\\boxed\s*\{")
_TOKEN_RE = re.compile(r"\w+|[^\w\s]")


def _has_boxed(text: str) -> bool:
    for m in _BOXED_RE.finditer(text):
        close = _match_brace(text, m.end() - 1)
        if close is not None and text[m.end():close].strip():
            return True
    return False


def _tag_check(text: str, tags: Sequence[str]) -> tuple[bool, str]:
    pos = 0
    for tag in tags:
        open_, close = f"<{tag}>", f"</{tag}>"
        n_open, n_close = text.count(open_), text.count(close)
        if n_open == 0 or n_close == 0:
            return False, f"missing <{tag}> tag"
        if n_open > 1 or n_close > 1:
            return False, f"repeated <{tag}> tag"
        start = text.find(open_)
        end = text.find(close)
        if end < start:
            return False, f"<{tag}> closed before it opens"
        if start < pos:
            return False, f"tags out of order: <{tag}> must come after the previous tag"
        if not text[start + len(open_):end].strip():
            return False, f"empty <{tag}> tag"
        pos = end + len(close)
    return True, "ok"


class FormatVerifier(Verifier):
    """Required answer format: boxed answer / answer tags / a custom regex (see module docstring)."""

    name = "format"
    description = "answer format: \\boxed{} or <answer> present (configurable tags / regex)"
    timeout_s = 2.0
    in_process = True

    def __init__(self, *, tags: str | Sequence[str] | None = None, boxed: bool | None = None,
                 pattern: str | None = None, full_match: bool = False, partial: bool = False):
        if isinstance(tags, str):
            tags = (tags,)
        self.tags = tuple(tags) if tags else ()
        for tag in self.tags:
            if not re.fullmatch(r"[A-Za-z_][\w-]*", tag):
                raise ValueError(f"format verifier: bad tag name {tag!r}")
        self.boxed = bool(boxed)
        self.pattern = pattern
        try:
            self._regex = re.compile(pattern, re.DOTALL) if pattern is not None else None
        except re.error as e:
            raise ValueError(f"format verifier: invalid regex {pattern!r}: {e}") from None
        self.full_match = full_match
        self.partial = partial
        self.default = not self.tags and not self.boxed and pattern is None

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state.pop("_regex", None)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._regex = re.compile(self.pattern, re.DOTALL) if self.pattern is not None else None

    def check(self, completion: str, reference: Any) -> Verdict:
        if not isinstance(completion, str):
            raise TypeError(f"format verifier: completion must be a str, got {type(completion).__name__}")
        checks: dict[str, bool] = {}
        failures: list[str] = []
        if self.default:
            ok = _has_boxed(completion) or _tag_check(completion, ("answer",))[0]
            checks["boxed or answer tag"] = ok
            if not ok:
                failures.append("no \\boxed{} or <answer> tag")
        if self.tags:
            ok, why = _tag_check(completion, self.tags)
            checks["tags " + ",".join(self.tags)] = ok
            if not ok:
                failures.append(why)
        if self.boxed:
            ok = _has_boxed(completion)
            checks["boxed"] = ok
            if not ok:
                failures.append("no non-empty \\boxed{}")
        if self._regex is not None:
            ok = bool(self._regex.fullmatch(completion.strip()) if self.full_match else self._regex.search(completion))
            checks["pattern"] = ok
            if not ok:
                failures.append("pattern did not match")
        met = sum(checks.values())
        if not failures:
            return Verdict(1.0, "ok", {"checks": checks})
        score = met / len(checks) if self.partial else 0.0
        return Verdict(score, failures[0], {"checks": checks})


class LengthVerifier(Verifier):
    """1 within a length budget, linear decay to 0 beyond it (see module docstring)."""

    name = "length"
    description = "length budget: 1 within max chars/tokens, linear decay to 0 beyond"
    timeout_s = 2.0
    in_process = True

    def __init__(self, max_chars: int | None = None, max_tokens: int | None = None, *,
                 window: int | None = None, tokenizer: Callable[[str], Any] | None = None):
        if max_chars is not None and max_tokens is not None:
            raise ValueError("length verifier: give max_chars or max_tokens, not both")
        if max_chars is None and max_tokens is None:
            max_chars = 4000
        budget = max_chars if max_chars is not None else max_tokens
        if isinstance(budget, bool) or not isinstance(budget, int) or budget < 1:
            raise ValueError(f"length verifier: the budget must be a positive int, got {budget!r}")
        if window is not None and (isinstance(window, bool) or not isinstance(window, int) or window < 1):
            raise ValueError(f"length verifier: window must be a positive int, got {window!r}")
        if tokenizer is not None and max_tokens is None:
            raise ValueError("length verifier: tokenizer= only makes sense with max_tokens=")
        self.unit = "chars" if max_chars is not None else "tokens"
        self.budget = budget
        self.window = window or budget
        self.tokenizer = tokenizer

    def measure(self, completion: str) -> int:
        if self.unit == "chars":
            return len(completion)
        if self.tokenizer is not None:
            out = self.tokenizer(completion)
            return out if isinstance(out, int) else len(out)
        return sum(1 for _ in _TOKEN_RE.finditer(completion))

    def check(self, completion: str, reference: Any) -> Verdict:
        if not isinstance(completion, str):
            raise TypeError(f"length verifier: completion must be a str, got {type(completion).__name__}")
        n = self.measure(completion)
        details = {"length": n, "budget": self.budget, "window": self.window, "unit": self.unit}
        if n <= self.budget:
            return Verdict(1.0, "within budget", details)
        score = max(0.0, 1.0 - (n - self.budget) / self.window)
        details["over_by"] = n - self.budget
        return Verdict(score, "over budget", details)
