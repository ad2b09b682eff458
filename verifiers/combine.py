"""Weighted composition: several verifiers scored as one (e.g. correctness 0.9 + format 0.1).

    from posttrain.verifiers import WeightedVerifier, combine, get_verifier
    reward = WeightedVerifier([(get_verifier("math"), 0.9), (get_verifier("format", tags="answer"), 0.1)])
    reward = combine(("math", 0.9), (get_verifier("format", tags="answer"), 0.1))   # names resolved
    reward = get_verifier("0.9*math + 0.1*format")          # the same, from a config string

`WeightedVerifier` takes verifier objects only; `combine` (in `posttrain.verifiers.registry`, which resolves
names) and `get_verifier`'s composition specs build one from names. So this module needs nothing but
`posttrain.verifiers.base`, and the registry builds on it, never the other way round.

score = sum(w_i * s_i) / sum(w_i) (exactly 1.0 when every part scores 1.0, so `passed` means
every part passed); reason = "name: reason; name: reason" in the order given; details =
{"parts": {name: {"weight": w, "score": s, "reason": r, "details": {...}}}}. Every part
receives the same completion and reference. A composition is itself a Verifier: it can be
registered, audited, nested and sent to worker processes (all parts run in the same worker,
under the sum of their time limits). It runs in-process only when every part may.
Deterministic when its parts are.
"""
from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier


class WeightedVerifier(Verifier):
    """A weighted mean of verifiers (see module docstring)."""

    description = "weighted mean of several verifiers"

    def __init__(self, parts: Iterable[tuple[Verifier, float]] | Mapping[Verifier, float], *, name: str | None = None):
        items = list(parts.items()) if isinstance(parts, Mapping) else list(parts)
        if not items:
            raise ValueError("a weighted composition needs at least one (verifier, weight) part")
        resolved: list[tuple[str, Verifier, float]] = []
        seen: dict[str, int] = {}
        for entry in items:
            if not (isinstance(entry, tuple) and len(entry) == 2):
                raise ValueError(f"composition parts are (verifier, weight) pairs, got {entry!r}")
            verifier, weight = entry
            if isinstance(verifier, str):
                raise ValueError(f"composition part {verifier!r} is a name, not a Verifier: resolve it with "
                                 f"get_verifier({verifier!r}), or build the composition with posttrain.verifiers.combine()")
            if not isinstance(verifier, Verifier):
                raise ValueError(f"composition part {verifier!r} is not a Verifier")
            if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight) or weight < 0:
                raise ValueError(f"weight for {verifier.name!r} must be a finite number >= 0, got {weight!r}")
            base = verifier.name or type(verifier).__name__
            seen[base] = seen.get(base, 0) + 1
            label = base if seen[base] == 1 else f"{base}#{seen[base]}"
            resolved.append((label, verifier, float(weight)))
        total = math.fsum(w for _, _, w in resolved)
        if total <= 0:
            raise ValueError("composition weights must not all be zero")
        self.parts = resolved
        self.total_weight = total
        self.name = name or "+".join(f"{w:g}*{label}" for label, _, w in resolved)
        self.timeout_s = math.fsum(v.timeout_s for _, v, _ in resolved)
        self.in_process = all(v.in_process for _, v, _ in resolved)

    def warmup(self) -> None:
        for _, verifier, _ in self.parts:
            verifier.warmup()

    def check(self, completion: str, reference: Any) -> Verdict:
        verdicts = [(label, verifier.check(completion, reference), w) for label, verifier, w in self.parts]
        for label, v, _ in verdicts:
            if not isinstance(v, Verdict):
                raise TypeError(f"composition part {label!r} returned {type(v).__name__}, expected a Verdict")
        if all(v.score >= 1.0 for _, v, _ in verdicts):
            score = 1.0
        else:
            score = math.fsum(w * v.score for _, v, w in verdicts) / self.total_weight
            score = min(1.0, max(0.0, score))
            if score >= 1.0:  # rounding must not turn a failed part into a pass
                score = math.nextafter(1.0, 0.0)
        reason = "; ".join(f"{label}: {v.reason}" for label, v, _ in verdicts)
        details = {"parts": {label: {"weight": w, **v.to_dict()} for label, v, w in verdicts}}
        return Verdict(score, reason, details)

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        """The problems of the first part that ships some."""
        for _, verifier, _ in self.parts:
            try:
                return verifier.audit_problems(n, seed)
            except NotImplementedError:
                continue
        raise NotImplementedError(f"no part of {self.name!r} ships audit problems; pass --problems FILE.jsonl")
