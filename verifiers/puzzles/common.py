"""What the puzzle families share: answer scoping, seeded generators, the audit plumbing.

Answer scope (the same rule as the math verifier, so one completion format serves all):
if the completion holds a closed ``<answer>...</answer>`` pair, only the content of the
*last* pair counts; otherwise the text after the last ``</think>`` (or the whole text),
and inside it the last ``\\boxed{...}`` when there is one. Each family then reads its
answer from that scope (a family-specific fallback finds the answer in free text).
"""
from __future__ import annotations

import random
import re
from typing import Any, Callable, Literal

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier

Split = Literal["train", "test"]

_ANSWER_TAG = re.compile(r"<answer>(.*?)</answer>", re.S | re.I)
MAX_SCOPE_CHARS = 20_000  # an answer longer than this is not an answer


def answer_scope(completion: str) -> tuple[str, str]:
    """(scope, rule): where the answer is read from; rule is "answer tag", "boxed" or "text"."""
    tags = _ANSWER_TAG.findall(completion)
    if tags:
        return tags[-1].strip(), "answer tag"
    text = completion.rsplit("</think>", 1)[-1]
    boxed = last_boxed(text)
    if boxed is not None:
        return boxed.strip(), "boxed"
    return text, "text"


def last_boxed(text: str) -> str | None:
    """Content of the last ``\\boxed{...}`` / ``\\fbox{...}`` with balanced braces, or None."""
    start = max(text.rfind("\\boxed{"), text.rfind("\\fbox{"))
    if start < 0:
        return None
    i = text.index("{", start) + 1
    depth = 1
    for j in range(i, len(text)):
        c = text[j]
        if c == "{" and text[j - 1] != "\\":
            depth += 1
        elif c == "}" and text[j - 1] != "\\":
            depth -= 1
            if depth == 0:
                return text[i:j]
    return None


def strip_markup(text: str, keep_stars: bool = False) -> str:
    """Drop markdown emphasis/code marks and LaTeX text wrappers that models put around answers.

    `keep_stars`: leave `*` alone (it is multiplication in arithmetic answers).
    """
    text = re.sub(r"\\(?:text|textbf|mathrm|mathbf|emph)\{([^{}]*)\}", r"\1", text)
    return re.sub(r"[`_]+" if keep_stars else r"[*`_]+", "", text)


def make_rng(family: str, seed: int, split: str, difficulty: int) -> random.Random:
    """A generator RNG that depends on everything that defines the problem stream (str seeds are stable)."""
    return random.Random(f"posttrain/{family}/{split}/{difficulty}/{seed}")


def check_generate_args(n: int, split: str, difficulty: int, difficulties: range) -> None:
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"generate: n must be a non-negative int, got {n!r}")
    if split not in ("train", "test"):
        raise ValueError(f"generate: split must be 'train' or 'test', got {split!r}")
    if difficulty not in difficulties:
        raise ValueError(f"generate: difficulty must be in {difficulties.start}..{difficulties.stop - 1}, got {difficulty!r}")


def generate_unique(n: int, rng: random.Random, make: Callable[[random.Random], dict[str, Any] | None],
                    key: Callable[[dict[str, Any]], Any], what: str, max_tries_per_item: int = 200,
                    compatible: Callable[[dict[str, Any]], bool] | None = None) -> list[dict[str, Any]]:
    """Draw `n` problems from `make` (None means "retry"), skipping duplicate keys.

    `compatible(item)` may veto an item given the ones accepted so far (it keeps its own
    state), e.g. so that no problem's gold also solves another problem of the batch.
    """
    out: list[dict[str, Any]] = []
    seen: set[Any] = set()
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > max_tries_per_item * (n + 1):
            raise RuntimeError(f"{what}: could not generate {n} distinct problems (got {len(out)}); "
                               "lower n or change the difficulty")
        item = make(rng)
        if item is None:
            continue
        k = key(item)
        if k in seen or (compatible is not None and not compatible(item)):
            continue
        seen.add(k)
        out.append(item)
    return out


class PuzzleVerifier(Verifier):
    """A family verifier: `check`, plus `generate` and the audit hooks built on it."""

    family: str = ""
    default_difficulty: int = 2
    timeout_s = 5.0

    @staticmethod
    def generate(n: int, seed: int = 0, split: Split = "train", difficulty: int = 2) -> list[dict[str, Any]]:
        raise NotImplementedError

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        items = type(self).generate(n, seed, "train", self.default_difficulty)
        return [AuditProblem(prompt=x["prompt"], reference=x["reference"], gold=x["gold"]) for x in items]

    def check(self, completion: str, reference: Any) -> Verdict:
        ref = self.parse_reference(reference)
        if not isinstance(completion, str) or not completion.strip():
            return Verdict(0.0, "no answer found", {"rule": None})
        scope, rule = answer_scope(completion)
        if len(scope) > MAX_SCOPE_CHARS and rule != "text":
            return Verdict(0.0, "answer too long", {"rule": rule})
        return self.check_scope(scope, rule, ref)

    def parse_reference(self, reference: Any) -> Any:
        raise NotImplementedError

    def check_scope(self, scope: str, rule: str, ref: Any) -> Verdict:
        raise NotImplementedError


def require(condition: bool, message: str) -> None:
    """Reference validation: a malformed reference is the problem set's bug, so it raises."""
    if not condition:
        raise ValueError(message)
