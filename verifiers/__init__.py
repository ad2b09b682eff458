"""The verifier layer: score a completion against a reference, under hard limits, without torch.

    from posttrain.verifiers import get_verifier, score_batch, VerifierPool, combine, run_audit
    math = get_verifier("math")
    verdicts = score_batch(math, completions, answers, workers=2, timeout_s=5)

See verifiers/README.md (interface, contract, discovery, timeouts, audit, writing a verifier).
Imports only the standard library here; sympy is imported on first use by the math verifier.
"""
from __future__ import annotations

from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier
from posttrain.verifiers.combine import WeightedVerifier
from posttrain.verifiers.registry import FunctionVerifier, combine, get_verifier, list_verifiers
from posttrain.verifiers.runner import VerifierError, VerifierPool, default_workers, score_batch, score_one

_LAZY = {
    "MathVerifier": "posttrain.verifiers.math_answer",
    "FormatVerifier": "posttrain.verifiers.format",
    "LengthVerifier": "posttrain.verifiers.format",
    "run_audit": "posttrain.verifiers.audit",
    "AuditReport": "posttrain.verifiers.audit",
    "AuditCase": "posttrain.verifiers.audit",
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
    raise AttributeError(f"module 'posttrain.verifiers' has no attribute {name!r}")
