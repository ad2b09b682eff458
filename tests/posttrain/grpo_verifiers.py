"""Verifiers for tests/posttrain/trainers/test_grpo.py (and rollout/test_backends.py, test_real_models.py), loaded as `tests/posttrain/grpo_verifiers.py:NAME` (worker processes
import this file by path). Deterministic: whatever they do depends only on the completion text (and, for
`half_on_odd`, the reference)."""
import os
import time
import zlib


def digits(completion, reference):
    """An easy verifiable reward: the fraction of the completion's characters that are digits."""
    return sum(c.isdigit() for c in completion) / len(completion) if completion else 0.0


def constant(completion, reference):
    """The same reward for everything: every group is degenerate."""
    return 0.0


def _h(completion: str) -> int:
    return zlib.crc32(completion.encode())


def hang_or_crash(completion, reference):
    """Worked solutions pass; a quarter of other completions hang forever, a quarter kill their worker."""
    if "<answer>" in completion:
        return 1.0
    h = _h(completion) % 4
    if h == 0:
        time.sleep(3600)
    if h == 1:
        os._exit(3)
    return 0.5 if h == 2 else 0.0


def raises_sometimes(completion, reference):
    """Worked solutions pass; about half of other completions make it raise (a verifier bug)."""
    if "<answer>" in completion:
        return 1.0
    if _h(completion) % 2 == 0:
        raise ValueError("cannot handle this completion")
    return 0.0


def always_raises(completion, reference):
    """A broken verifier."""
    raise ValueError("broken verifier")


def half_on_odd(completion, reference):
    """Problems whose reference hashes even are always solved; the others pass about half their completions."""
    if zlib.crc32(repr(reference).encode()) % 2 == 0:
        return 1.0
    return float(_h(completion) % 2)
