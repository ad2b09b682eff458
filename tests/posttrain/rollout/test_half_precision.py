"""The lean decoder on half-precision (bf16 / fp16) model weights: accepted by lean_support, logits within half
rounding of the HF forward run in the same dtype (prefill and decode steps, left-padded, GQA, biases), greedy
tokens equal to the HF backend's on most rows, sampling log-probs equal to `batched_logprobs` recomputed on the
same bf16 model within bf16 rounding; and what the engine picks for each precision (CPU here; the CUDA choices
are in the CUDA test at the end, which skips without a GPU)."""
from __future__ import annotations

import copy

import pytest
import torch

from posttrain.lean.support import lean_support
from posttrain.logprobs import batched_logprobs
from posttrain.rollout import LeanLlama, collate_rollouts, generate, select_backend

pytestmark = pytest.mark.usefixtures("one_thread")  # correctness tests (tests/conftest.py)

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")  # (besides `cuda`)


def _batch(V: int, steps: int):
    g = torch.Generator().manual_seed(1)
    seqs = [torch.randint(3, V, (n,), generator=g).tolist() for n in (5, 11, 8)]
    T = max(map(len, seqs))
    ids = torch.zeros(len(seqs), T, dtype=torch.long)
    am = torch.zeros(len(seqs), T, dtype=torch.long)
    for i, s in enumerate(seqs):
        ids[i, T - len(s):] = torch.tensor(s)
        am[i, T - len(s):] = 1
    nxt = torch.randint(3, V, (len(seqs), steps), generator=g)
    return ids, am, nxt


def _hf_and_lean(model, steps: int = 3, static: bool = False):
    """Logits (B, 1 + steps, V) fp32 at the last prompt position and each decode step: (HF forward, lean)."""
    V = model.config.vocab_size
    ids, am, nxt = _batch(V, steps)
    B, T = ids.shape
    ids2 = torch.cat([ids, nxt], 1)
    am2 = torch.cat([am, torch.ones(B, steps, dtype=am.dtype)], 1)
    pos, pos2 = (am.cumsum(-1) - 1).clamp(min=0), (am2.cumsum(-1) - 1).clamp(min=0)
    with torch.no_grad():
        ref = model(input_ids=ids2, attention_mask=am2, position_ids=pos2).logits[:, T - 1:].float()
    lean = LeanLlama(model)
    out = []
    with torch.inference_mode():
        lean.start(B, T + steps, T + steps + 4, static=static)
        out.append(lean.prefill(ids, am.bool(), pos, torch.arange(B)).float())
        if static:
            lean.st.pos.copy_(am.sum(-1))
            lean.st.col.fill_(T)
        for s in range(steps):
            if static:
                lean.st.tok.copy_(nxt[:, s:s + 1])
                out.append(lean.step())
                lean.st.pos.add_(1)
                lean.st.col.add_(1)
            else:
                out.append(lean.decode(nxt[:, s:s + 1], pos2[:, T + s], T + s).float())
    return ref, torch.stack(out, 1)


def test_lean_support_accepts_half_weights_and_refuses_other_dtypes(small_llama):
    for dt in (torch.bfloat16, torch.float16):
        ok, why = lean_support(small_llama("llama-gqa", dtype=dt), 64, mode="decode")
        assert ok and str(dt).removeprefix("torch.") in why, why
        assert not lean_support(small_llama("llama-gqa", dtype=dt), 64, mode="train")[0]  # train mode unchanged: fp32 only
    ok, why = lean_support(small_llama("llama-gqa", dtype=torch.float64), 64, mode="decode")
    assert not ok and why == "dtype torch.float64 (the lean decoder runs fp32, bf16 or fp16 weights)"


@pytest.mark.parametrize("static", [False, True], ids=["decode", "static-step"])
@pytest.mark.parametrize("dt", [torch.bfloat16, torch.float16], ids=["bf16", "fp16"])
@pytest.mark.parametrize("kind", ["llama-gqa", "qwen2"])
def test_half_lean_logits_match_the_hf_forward_in_the_same_dtype(kind, dt, static, small_llama):
    """Prefill and 3 decode steps: lean in bf16 (fp16) vs HF in bf16 (fp16), both measured against the fp32 HF
    forward. Two half computations round differently; the lean one must be as close to fp32 as HF's is."""
    fp32 = small_llama(kind)
    ref32, _ = _hf_and_lean(fp32)
    ref, got = _hf_and_lean(copy.deepcopy(fp32).to(dt), static=static)
    lean = LeanLlama(copy.deepcopy(fp32).to(dt))
    assert lean.dtype == lean.weight_dtype == lean.layers[0][1].dtype == dt and not lean.packed
    scale = ref32.abs().amax(-1, keepdim=True)  # (B, steps, 1): each position's logit scale
    err_lean = float(((got - ref) / scale).abs().max())
    err_hf = float(((ref - ref32) / scale).abs().max())
    err_lean32 = float(((got - ref32) / scale).abs().max())
    unit = 2.0 ** -8 if dt == torch.bfloat16 else 2.0 ** -11  # relative rounding of the half dtype
    print(f"{kind} {dt}: |lean-hf| {err_lean:.4f}, |hf-fp32| {err_hf:.4f}, |lean-fp32| {err_lean32:.4f}")
    # a few layers of half rounding: HF's own distance from fp32 is ~10-20 units here (measured 0.038 bf16, 0.005
    # fp16); the lean path must be no further from fp32 than twice that, and within 24 units of HF's numbers
    assert err_lean < 24 * unit and err_lean32 < 24 * unit
    assert err_lean32 <= 2 * err_hf + unit
    assert (got.argmax(-1) == ref.argmax(-1)).float().mean() >= 0.9


def test_half_static_step_equals_half_decode(small_llama):
    model = small_llama("llama-gqa", dtype=torch.bfloat16)
    _, a = _hf_and_lean(model)
    _, b = _hf_and_lean(model, static=True)
    torch.testing.assert_close(b, a, atol=2.0 ** -7 * float(a.abs().max()), rtol=0)


def test_bf16_model_selects_the_lean_decoder_and_fp32_paths_are_unchanged(trained_lm):
    model, tok, _ = trained_lm
    bf16 = copy.deepcopy(model).to(torch.bfloat16)
    fwd, why = select_backend(bf16, 64)
    assert fwd.name == "lean" and fwd.dtype == fwd.weight_dtype == torch.bfloat16 and "bfloat16 weights" in why
    # on CPU: fp32 weights compute fp32; rollout.dtype=bfloat16 keeps bf16 weight copies under fp32 activations
    fwd = select_backend(model, 64, dtype="bfloat16")[0]
    assert fwd.dtype == torch.float32 and fwd.weight_dtype == torch.bfloat16
    assert select_backend(model, 64)[0].dtype == select_backend(model, 64)[0].weight_dtype == torch.float32
    with torch.autocast("cpu", dtype=torch.bfloat16):  # CPU autocast: the HF forward, as before
        fwd, why = select_backend(model, 64)
        assert fwd.name == "hf" and "autocast" in why


def test_bf16_greedy_matches_the_hf_backend_on_most_rows(trained_lm):
    """Tolerance: bf16 rounding differs between the two paths (~2^-8 of the logit scale), so a greedy step whose
    top-2 logits are that close may flip and the rows diverge from there. At least 5 of the 6 rows must agree
    token for token (24 tokens), and every row must agree up to its first step where the HF bf16 top-2 margin
    is < 0.25 (a near-tie)."""
    model, tok, prompts = trained_lm
    bf16 = copy.deepcopy(model).to(torch.bfloat16)
    lean = generate(bf16, tok, prompts, greedy=True, max_new_tokens=24)
    hf = generate(bf16, tok, prompts, greedy=True, max_new_tokens=24, backend="hf")
    same = [a.completion_ids == b.completion_ids for a, b in zip(lean, hf)]
    print("bf16 greedy rows equal to the HF backend:", same)
    assert sum(same) >= 5
    for a, b in zip(lean, hf):
        if a.completion_ids == b.completion_ids:
            assert a.finish_reason == b.finish_reason
            continue
        ids = torch.tensor([a.prompt_ids + b.completion_ids])
        with torch.no_grad():
            logits = bf16(input_ids=ids).logits[0, len(a.prompt_ids) - 1:].float()  # (n + 1, V)
        top2 = logits.topk(2, -1).values
        near = ((top2[:, 0] - top2[:, 1]) < 0.25).nonzero().view(-1)
        k = int(near[0]) if len(near) else len(b.completion_ids)
        assert a.completion_ids[:k] == b.completion_ids[:k]


def test_bf16_sampling_logprobs_match_recomputed_on_the_bf16_model(trained_lm):
    """The engine's log-probs on a bf16 model vs `batched_logprobs` (the HF forward of the same bf16 model): two
    bf16 computations of the same numbers. bf16 logits are rounded at ~2^-8 of their size (0.06 for a logit of 16),
    so single tokens can differ by a few tenths; the bound is relative to how far HF's own bf16 log-probs are from
    its fp32 ones on the same tokens: mean gap < 0.02, max gap <= 2 x HF's bf16-vs-fp32 max gap."""
    model, tok, prompts = trained_lm
    bf16 = copy.deepcopy(model).to(torch.bfloat16)
    rollouts = generate(bf16, tok, prompts, n=2, max_new_tokens=16, seed=3, temperature=0.8)
    batch = collate_rollouts(rollouts, tok.pad_token_id)
    mask = batch.completion_mask.bool()
    for temperature, got in ((1.0, batch.policy_logprobs), (0.8, batch.logprobs)):
        want, _ = batched_logprobs(bf16, batch, micro_batch_size=4, temperature=temperature)
        fp32, _ = batched_logprobs(model, batch, micro_batch_size=4, temperature=temperature)
        gap, hf_gap = (want - got)[mask].abs(), (want - fp32)[mask].abs()
        print(f"T={temperature}: |lean - HF bf16| max {float(gap.max()):.4f} mean {float(gap.mean()):.5f}; "
              f"|HF bf16 - HF fp32| max {float(hf_gap.max()):.4f} mean {float(hf_gap.mean()):.5f}")
        assert float(gap.mean()) < 0.02 and float(gap.max()) <= 2 * float(hf_gap.max()) + 0.05, temperature


@pytest.mark.cuda
@needs_cuda
def test_cuda_bf16_precision_choices_and_graph_generate(trained_lm):
    """On CUDA: bf16 weights, rollout.dtype=bfloat16 and bf16 autocast all compute in bf16 on the lean decoder;
    generation (static step, CUDA graph, EOS every 16 steps) gives the HF backend's greedy tokens on most rows."""
    model, tok, prompts = trained_lm
    cuda = copy.deepcopy(model).cuda()
    with torch.autocast("cuda", dtype=torch.bfloat16):
        fwd, why = select_backend(cuda, 64)
        assert fwd.name == "lean" and fwd.dtype == fwd.weight_dtype == torch.bfloat16, why
        lean = generate(cuda, tok, prompts, greedy=True, max_new_tokens=24)
    fwd = select_backend(cuda, 64, dtype="bfloat16")[0]
    assert fwd.dtype == fwd.weight_dtype == torch.bfloat16
    bf16 = copy.deepcopy(model).to("cuda", torch.bfloat16)
    assert select_backend(bf16, 64)[0].dtype == torch.bfloat16
    a = generate(bf16, tok, prompts, greedy=True, max_new_tokens=24)
    b = generate(bf16, tok, prompts, greedy=True, max_new_tokens=24, backend="hf")
    assert sum(x.completion_ids == y.completion_ids for x, y in zip(a, b)) >= 5
    assert sum(x.completion_ids == y.completion_ids for x, y in zip(lean, b)) >= 4
