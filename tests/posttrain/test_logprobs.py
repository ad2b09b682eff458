"""posttrain.logprobs: alignment, padding sides, gradients, entropy, micro-batching, masked reductions."""
from __future__ import annotations

import random

import pytest
import torch

from posttrain.logprobs import (
    batched_logprobs,
    masked_mean,
    masked_sum,
    masked_var,
    masked_whiten,
    sequence_logprobs,
    token_logprobs,
)
from posttrain.models import build_model, train_tokenizer


pytestmark = pytest.mark.usefixtures("one_thread")  # correctness tests (tests/conftest.py)


@pytest.fixture(scope="module")
def model():
    rng = random.Random(0)
    words = "alpha beta gamma delta one two three four red blue green".split()
    tok = train_tokenizer([" ".join(rng.choice(words) for _ in range(20)) for _ in range(100)], vocab_size=200)
    m = build_model("tiny", tok, seed=1).eval()
    with torch.no_grad():  # larger logits than the 0.02 init, so log-probs are far from uniform
        m.lm_head.weight.mul_(20)
    return m


def _seqs(n=4, seed=0, vocab=200):
    g = torch.Generator().manual_seed(seed)
    return [torch.randint(3, vocab, (int(torch.randint(4, 12, (1,), generator=g)),), generator=g).tolist()
            for _ in range(n)]


def _pad(seqs, side):
    T = max(map(len, seqs))
    ids = torch.zeros(len(seqs), T, dtype=torch.long)
    am = torch.zeros(len(seqs), T, dtype=torch.long)
    for i, s in enumerate(seqs):
        sl = slice(T - len(s), T) if side == "left" else slice(0, len(s))
        ids[i, sl] = torch.tensor(s)
        am[i, sl] = 1
    return ids, am


def _naive(model, seq, temperature=1.0):
    """log p(seq[t] | seq[:t]) for t >= 1 from a single unpadded forward and a full log_softmax."""
    with torch.no_grad():
        logits = model(input_ids=torch.tensor([seq])).logits[0].float() / temperature
    lsm = torch.log_softmax(logits, -1)
    return torch.stack([lsm[t - 1, seq[t]] for t in range(1, len(seq))])


@pytest.mark.parametrize("side", ["left", "right"])
def test_matches_unpadded_reference(model, side):
    seqs = _seqs()
    ids, am = _pad(seqs, side)
    with torch.no_grad():
        lp, ent = sequence_logprobs(model, ids, am, return_entropy=True)
    assert lp.shape == ids.shape and ent.shape == ids.shape
    T = ids.shape[1]
    for i, s in enumerate(seqs):
        off = T - len(s) if side == "left" else 0
        got = lp[i, off + 1:off + len(s)]
        torch.testing.assert_close(got, _naive(model, s), atol=1e-4, rtol=1e-6)
        assert lp[i, off] == 0 and (lp[i] * (1 - am[i])).abs().sum() == 0  # no log-prob for first/pad tokens


def test_completion_mask_temperature_and_entropy(model):
    seqs = _seqs(3, seed=1)
    ids, am = _pad(seqs, "left")
    cm = torch.zeros_like(am)
    cm[:, -3:] = 1  # score only the last 3 tokens (what a RolloutBatch completion looks like)
    with torch.no_grad():
        lp, ent = sequence_logprobs(model, ids, am, cm, temperature=0.7, return_entropy=True)
    assert (lp[:, :-3] == 0).all() and (ent[:, :-3] == 0).all()
    for i, s in enumerate(seqs):
        torch.testing.assert_close(lp[i, -3:], _naive(model, s, 0.7)[-3:], atol=1e-4, rtol=1e-6)
        with torch.no_grad():
            logits = model(input_ids=torch.tensor([s])).logits[0, -4:-1].float() / 0.7
        p = torch.softmax(logits, -1)
        torch.testing.assert_close(ent[i, -3:], -(p * p.log()).sum(-1), atol=1e-4, rtol=1e-6)


def test_entropy_without_gradient_is_the_same_number(model):
    seqs = _seqs(2, seed=3)
    ids, am = _pad(seqs, "left")
    lp1, e1 = sequence_logprobs(model, ids, am, return_entropy=True)
    lp2, e2 = sequence_logprobs(model, ids, am, return_entropy=True, entropy_grad=False)
    assert e1.requires_grad and not e2.requires_grad and lp2.requires_grad
    torch.testing.assert_close(e1.detach(), e2, atol=0, rtol=0)
    torch.testing.assert_close(lp1, lp2, atol=0, rtol=0)


def test_gradients_match_naive(model):
    seqs = _seqs(2, seed=2)
    ids, am = _pad(seqs, "left")
    model.zero_grad()
    lp, _ = sequence_logprobs(model, ids, am)
    lp.sum().backward()
    g1 = model.lm_head.weight.grad.clone()
    model.zero_grad()
    total = 0
    for s in seqs:
        logits = model(input_ids=torch.tensor([s])).logits[0]
        lsm = torch.log_softmax(logits, -1)
        total = total + sum(lsm[t - 1, s[t]] for t in range(1, len(s)))
    total.backward()
    torch.testing.assert_close(g1, model.lm_head.weight.grad, atol=1e-4, rtol=1e-4)
    model.zero_grad()


def test_batched_equals_full_and_trims(model):
    seqs = _seqs(5, seed=3)
    ids, am = _pad(seqs, "left")
    with torch.no_grad():
        full, _ = sequence_logprobs(model, ids, am)
    batched, ent = batched_logprobs(model, {"input_ids": ids, "attention_mask": am}, micro_batch_size=2,
                                    return_entropy=True)
    torch.testing.assert_close(batched, full, atol=1e-4, rtol=1e-6)
    assert ent is not None and ent.shape == ids.shape
    with pytest.raises(ValueError, match="micro_batch_size"):
        batched_logprobs(model, {"input_ids": ids, "attention_mask": am}, micro_batch_size=0)


@pytest.mark.parametrize("side", ["left", "right"])
def test_batched_by_length_puts_every_row_back_in_its_place(model, side):
    """Long and short rows interleaved: grouped by length, the micro-batches are rows 0, 2, 4 and 1, 3, 5 (not
    consecutive), and each row's log-probs and entropies land in its own row."""
    seqs = [s + s[:6] if i % 2 == 0 else s[:4] for i, s in enumerate(_seqs(6, seed=5))]
    ids, am = _pad(seqs, side)
    with torch.no_grad():
        lp_one, ent_one = zip(*(sequence_logprobs(model, ids[i:i + 1], am[i:i + 1], return_entropy=True)
                                for i in range(len(seqs))))
    batched, ent = batched_logprobs(model, {"input_ids": ids, "attention_mask": am}, micro_batch_size=3,
                                    return_entropy=True)
    torch.testing.assert_close(batched, torch.cat(lp_one), atol=1e-4, rtol=1e-6)
    torch.testing.assert_close(ent, torch.cat(ent_one), atol=1e-4, rtol=1e-6)
    assert (batched[am == 0] == 0).all()


def test_wrapped_model(model):
    class Wrapper(torch.nn.Module):  # stands in for DDP / accelerate wrappers: forwards to .module
        def __init__(self, m):
            super().__init__()
            self.module = m

        def forward(self, **kw):
            return self.module(**kw)

    ids, am = _pad(_seqs(2, seed=4), "left")
    with torch.no_grad():
        a, _ = sequence_logprobs(model, ids, am)
        b, _ = sequence_logprobs(Wrapper(model), ids, am)
    torch.testing.assert_close(a, b)


def test_token_logprobs_small_example():
    logits = torch.tensor([[0.0, 1.0, 2.0]])
    lp, ent = token_logprobs(logits, torch.tensor([2]), return_entropy=True)
    p = torch.softmax(logits, -1)
    torch.testing.assert_close(lp, p[:, 2].log())
    torch.testing.assert_close(ent, -(p * p.log()).sum(-1))


def test_masked_reductions_by_hand():
    x = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    m = torch.tensor([[1, 1, 0], [0, 1, 0]])
    assert masked_sum(x, m).item() == 8.0
    torch.testing.assert_close(masked_sum(x, m, dim=1), torch.tensor([3.0, 5.0]))
    assert masked_mean(x, m).item() == pytest.approx(8.0 / 3)
    torch.testing.assert_close(masked_mean(x, m, dim=1), torch.tensor([1.5, 5.0]))
    torch.testing.assert_close(masked_mean(x, torch.zeros_like(m), dim=1), torch.zeros(2))  # empty -> 0, not NaN
    # values 1, 2, 5: mean 8/3, unbiased var = ((5/3)^2 + (2/3)^2 + (7/3)^2) / 2 = 13/3
    assert masked_var(x, m).item() == pytest.approx(13.0 / 3)
    assert masked_var(x, m, unbiased=False).item() == pytest.approx(26.0 / 9)
    w = masked_whiten(x, m)
    sel = w[m.bool()]
    assert sel.mean().item() == pytest.approx(0.0, abs=1e-6)
    assert sel.var().item() == pytest.approx(1.0, abs=1e-5)
    w2 = masked_whiten(x, m, shift_mean=False)
    assert w2[m.bool()].mean().item() == pytest.approx(8.0 / 3, abs=1e-5)


@pytest.mark.parametrize("kind", ["llama", "gpt2"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_left_padded_hf_forward_gets_a_mask_without_empty_rows_and_the_same_numbers(kind, dtype):
    """models.hf_attention_mask: with left padding, a 4D mask where each pad query sees itself; the real tokens'
    logits equal the 2D mask's (within rounding), and so do sequence_logprobs' (the HF path: bf16 weights or GPT-2)."""
    from transformers import GPT2Config, GPT2LMHeadModel, LlamaConfig, LlamaForCausalLM

    from posttrain.models import hf_attention_mask

    torch.manual_seed(0)
    if kind == "llama":
        model = LlamaForCausalLM(LlamaConfig(vocab_size=64, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                             num_attention_heads=4, num_key_value_heads=2))
    else:
        model = GPT2LMHeadModel(GPT2Config(vocab_size=64, n_embd=32, n_layer=2, n_head=4, bos_token_id=0,
                                           eos_token_id=0))
    model = model.to(dtype).eval()
    ids = torch.randint(3, 60, (3, 9))
    am = torch.ones(3, 9, dtype=torch.long)
    am[0, :4], am[1, :2] = 0, 0
    four = hf_attention_mask(am, model)
    assert four.shape == (3, 1, 9, 9) and bool(four.any(-1).all())  # no query row without a key
    assert hf_attention_mask(torch.ones(2, 5, dtype=torch.long), model).shape == (2, 5)  # no left padding: 2D
    pos = (am.cumsum(-1) - 1).clamp(min=0)
    with torch.no_grad():
        plain = model(input_ids=ids, attention_mask=am, position_ids=pos).logits.float()
        ours = model(input_ids=ids, attention_mask=four, position_ids=pos).logits.float()
        # the same function of the same numbers (equal here); a kernel chosen per mask kind may round differently
        tol = 1e-5 if dtype == torch.float32 else 2e-2
        assert torch.allclose(plain[am.bool()], ours[am.bool()], atol=tol, rtol=tol)
        lp, _ = sequence_logprobs(model, ids, am)
        ref = torch.log_softmax(plain[:, :-1], -1).gather(-1, ids[:, 1:, None])[..., 0]  # (B, T-1)
        m = (am[:, 1:] * am[:, :-1]).bool()
        assert torch.allclose(lp[:, 1:][m], ref[m], atol=1e-5)


def test_a_sliding_window_model_keeps_the_2d_mask():
    """A 4D mask would replace a sliding-window model's windows: such models get the plain 2D padding mask."""
    from transformers import MistralConfig, MistralForCausalLM

    from posttrain.models import hf_attention_mask, plain_causal_attention

    cfg = dict(vocab_size=64, hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=4,
               num_key_value_heads=2)
    windowed, plain = MistralForCausalLM(MistralConfig(sliding_window=4, **cfg)), \
        MistralForCausalLM(MistralConfig(sliding_window=None, **cfg))
    assert not plain_causal_attention(windowed) and plain_causal_attention(plain)
    am = torch.ones(2, 6, dtype=torch.long)
    am[0, :3] = 0
    assert hf_attention_mask(am, windowed) is am and hf_attention_mask(am, plain).shape == (2, 1, 6, 6)
