"""The verifier layer: score a completion against a reference, under hard limits, without torch.

    from verifiers import get_verifier, score_batch, VerifierPool, combine, run_audit
    math = get_verifier("math")
    verdicts = score_batch(math, completions, answers, workers=2, timeout_s=5)

See verifiers/README.md (interface, contract, discovery, timeouts, audit, writing a verifier).
Imports only the standard library here; sympy is imported on first use by the math verifier.
"""
from __future__ import annotations

from typing import Any

from verifiers.base import AuditProblem, Verdict, Verifier
from verifiers.combine import WeightedVerifier
from verifiers.registry import FunctionVerifier, combine, get_verifier, list_verifiers
from verifiers.runner import VerifierError, VerifierPool, default_workers, score_batch, score_one

_LAZY = {
    "MathVerifier": "verifiers.math_answer",
    "FormatVerifier": "verifiers.format",
    "LengthVerifier": "verifiers.format",
    "run_audit": "verifiers.audit",
    "AuditReport": "verifiers.audit",
    "AuditCase": "verifiers.audit",
}

__all__ = [
    "AuditProblem", "Verdict", "Verifier", "WeightedVerifier", "combine", "FunctionVerifier",
    "get_verifier", "list_verifiers", "VerifierError", "VerifierPool", "default_workers",
    "score_batch", "score_one", *_LAZY,
]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'verifiers' has no attribute {name!r}")
