"""`extend` (several tokens per row in one step, the multi-turn loop's prefill of an environment message) against
feeding the same tokens one decode step at a time with the idle rows' columns masked, as the loop did before:
the same logits at each row's last token and after one more decode step (fp32 rounding; bf16: its rounding), on
the lean decoder (fp32 and bf16 compute; Llama with GQA, Qwen2 with biases) and on the Hugging Face forward."""
from __future__ import annotations

import pytest
import torch

from posttrain.rollout import LeanLlama
from posttrain.rollout.backends import HFForward
from posttrain.rollout.multiturn import _hide

pytestmark = pytest.mark.usefixtures("one_thread")

FEEDS = [[11, 12, 13, 14], [21], [], [31, 32]]  # per row: the tokens of this step (row 2 is idle)
NEXT = [41, 42, 43, 44]


def _prefill(fwd, cols):
    g = torch.Generator().manual_seed(1)
    seqs = [torch.randint(3, 97, (n,), generator=g).tolist() for n in (5, 11, 8, 3)]
    B, T = len(seqs), max(map(len, seqs))
    ids, am = torch.zeros(B, T, dtype=torch.long), torch.zeros(B, T, dtype=torch.long)
    for i, s in enumerate(seqs):
        ids[i, T - len(s):] = torch.tensor(s)
        am[i, T - len(s):] = 1
    fwd.start(B, T + cols, T + cols + 4)
    fwd.prefill(ids, am.bool(), (am.cumsum(-1) - 1).clamp(min=0), torch.arange(B))
    return am.sum(-1).tolist(), T


def _one_by_one(fwd):
    """Each row's tokens one decode step at a time; rows with nothing left feed a pad whose column is masked."""
    pos, col = _prefill(fwd, 8)
    last = [None] * len(FEEDS)
    for s in range(max(map(len, FEEDS))):
        fed = [b for b, f in enumerate(FEEDS) if s < len(f)]
        tok = torch.tensor([[f[s] if s < len(f) else 0] for f in FEEDS])
        logits = fwd.decode(tok, torch.tensor(pos), col)
        idle = [b for b in range(len(FEEDS)) if b not in fed]
        if idle:
            _hide(fwd, idle, col)
        col += 1
        for b in fed:
            pos[b] += 1
            last[b] = logits[b].float().clone()
    after = fwd.decode(torch.tensor(NEXT).view(-1, 1), torch.tensor(pos), col).float()
    return last, after


def _chunked(fwd):
    pos, col = _prefill(fwd, 8)
    B, K = len(FEEDS), max(map(len, FEEDS))
    tok = torch.zeros(B, K, dtype=torch.long)
    valid = torch.zeros(B, K, dtype=torch.bool)
    p = torch.tensor(pos)[:, None] + torch.arange(K)
    for b, f in enumerate(FEEDS):
        tok[b, :len(f)] = torch.tensor(f, dtype=torch.long)
        valid[b, :len(f)] = True
    at = torch.tensor([max(len(f) - 1, 0) for f in FEEDS])
    logits = fwd.extend(tok, valid, p, col, at).float()
    last = [logits[b].clone() if f else None for b, f in enumerate(FEEDS)]
    pos = [q + len(f) for q, f in zip(pos, FEEDS)]
    after = fwd.decode(torch.tensor(NEXT).view(-1, 1), torch.tensor(pos), col + K).float()
    return last, after


def _check(make, tol):
    with torch.inference_mode():
        a_last, a_after = _one_by_one(make())
        b_last, b_after = _chunked(make())
    scale = float(a_after.abs().max())
    for b, (x, y) in enumerate(zip(a_last, b_last)):
        assert (x is None) == (y is None)
        if x is not None:
            torch.testing.assert_close(y, x, atol=tol * scale, rtol=0, msg=f"row {b}'s last token")
    torch.testing.assert_close(b_after, a_after, atol=tol * scale, rtol=0)
    assert torch.isfinite(b_after).all()


@pytest.mark.parametrize("kind", ["llama-gqa", "qwen2"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16], ids=["fp32", "bf16"])
def test_lean_extend_equals_decode_steps(kind, dtype, small_llama):
    model = small_llama(kind)
    _check(lambda: LeanLlama(model, compute_dtype=dtype), 1e-5 if dtype == torch.float32 else 2.0 ** -6)


@pytest.mark.parametrize("kind", ["llama-gqa", "qwen2"])
def test_hf_extend_equals_decode_steps(kind, small_llama):
    model = small_llama(kind)
    _check(lambda: HFForward(model), 1e-5)
