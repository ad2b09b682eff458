"""posttrain.rollout: lean path == HF forward, greedy == model.generate, log-probs, finishing, seeding,
top-k / top-p, errors, save / load."""
from __future__ import annotations

import json

import pytest
import torch

from posttrain.logprobs import batched_logprobs
from posttrain.models import build_model, train_tokenizer
from posttrain.rollout import (
    LeanLlama,
    Rollout,
    SamplingParams,
    collate_rollouts,
    generate,
    load_rollouts,
    row_uniforms,
    save_rollouts,
    select_backend,
)
from posttrain.rollout.sampling import Sampler


pytestmark = pytest.mark.usefixtures("one_thread")  # correctness tests (tests/conftest.py)


@pytest.fixture(scope="module")
def trained(trained_lm):
    """A tiny model trained for a few seconds on templated sentences (conftest.py's `trained_lm`)."""
    return trained_lm


def _left_pad(seqs):
    T = max(map(len, seqs))
    ids = torch.zeros(len(seqs), T, dtype=torch.long)
    am = torch.zeros(len(seqs), T, dtype=torch.long)
    for i, s in enumerate(seqs):
        ids[i, T - len(s):] = torch.tensor(s)
        am[i, T - len(s):] = 1
    return ids, am


# ------------------------------------------------------------------ lean path == HF forward


@pytest.mark.parametrize("packed", [True, False], ids=["packed", "plain"])
@pytest.mark.parametrize("kind", ["tiny", "llama-gqa-scaled-rope", "mistral", "qwen2"])
def test_lean_logits_match_hf_prefill_and_decode(kind, packed, trained, monkeypatch, small_llama):
    from posttrain.lean import decode

    monkeypatch.setattr(decode, "PACK", packed)
    monkeypatch.setattr(decode, "PACK_MIN_HIDDEN", 0)  # the tiny configs are narrower than the default
    model = trained[0] if kind == "tiny" else small_llama(kind)
    assert select_backend(model, 64)[0].name == "lean"
    V = model.config.vocab_size
    g = torch.Generator().manual_seed(1)
    seqs = [torch.randint(3, V, (n,), generator=g).tolist() for n in (5, 11, 8)]
    ids, am = _left_pad(seqs)
    pos = (am.cumsum(-1) - 1).clamp(min=0)
    B, T = ids.shape
    nxt = torch.randint(3, V, (B, 4), generator=g)
    ids2, am2 = torch.cat([ids, nxt], 1), torch.cat([am, torch.ones(B, 4, dtype=am.dtype)], 1)
    pos2 = (am2.cumsum(-1) - 1).clamp(min=0)
    with torch.no_grad():
        ref = model(input_ids=ids2, attention_mask=am2, position_ids=pos2).logits  # (B, T+4, V)
    lean = LeanLlama(model)
    assert lean.packed == packed  # the CPU torch wheels build oneDNN: packed weights wherever the suite runs
    with torch.inference_mode():
        lean.start(B, T + 4, T + 8)
        got = lean.prefill(ids, am.bool(), pos, torch.arange(B))
        torch.testing.assert_close(got, ref[:, T - 1], atol=1e-4, rtol=0)
        for s in range(4):
            got = lean.decode(nxt[:, s:s + 1], pos2[:, T + s], T + s)
            torch.testing.assert_close(got, ref[:, T + s], atol=1e-4, rtol=0)


def test_models_narrower_than_pack_min_hidden_multiply_plain_wider_ones_packed():
    from transformers import LlamaConfig, LlamaForCausalLM

    from posttrain.lean import decode

    def model(d):
        return LlamaForCausalLM(LlamaConfig(vocab_size=64, hidden_size=d, intermediate_size=2 * d,
                                            num_hidden_layers=1, num_attention_heads=4, num_key_value_heads=2,
                                            max_position_embeddings=64)).eval()

    narrow, wide = model(decode.PACK_MIN_HIDDEN // 2), model(decode.PACK_MIN_HIDDEN)
    assert not LeanLlama(narrow).packed and not LeanLlama(narrow).head_w.is_mkldnn
    assert LeanLlama(wide).packed == decode.pack_available(torch.float32)  # true with the CPU torch wheels


@pytest.mark.parametrize("wdt", [None, torch.bfloat16], ids=["fp32", "bf16"])
def test_packed_weights_give_the_plain_matmuls_numbers(wdt, monkeypatch, small_llama):
    """Packed (oneDNN-layout) fused weights: the same logits as plain matmuls over the same weights (fp32 within
    fp32 rounding; bf16 weights: both round their matmul outputs to bf16), their dense form equals the plain
    matrices exactly, and `load` after an update repacks (the refreshed engine equals a fresh one)."""
    from posttrain.lean import decode

    if wdt is not None and not decode.pack_available(wdt):  # oneDNN without bf16 kernels on this CPU
        pytest.skip("no packed bf16 linear on this CPU")
    monkeypatch.setattr(decode, "PACK_MIN_HIDDEN", 0)
    model = small_llama("qwen2")  # biases on q/k/v too
    V = model.config.vocab_size
    g = torch.Generator().manual_seed(3)
    ids, am = _left_pad([torch.randint(3, V, (n,), generator=g).tolist() for n in (4, 9, 7)])
    pos = (am.cumsum(-1) - 1).clamp(min=0)
    B, T = ids.shape
    nxt = torch.randint(3, V, (B, 1), generator=g)

    def run(packed):
        monkeypatch.setattr(decode, "PACK", packed)
        lean = LeanLlama(model, weight_dtype=wdt)
        assert lean.packed == packed
        with torch.inference_mode():
            lean.start(B, T + 1, T + 4)
            first = lean.prefill(ids, am.bool(), pos, torch.arange(B))
            out = torch.cat([first, lean.decode(nxt, am.sum(-1), T)])
        return lean, out

    (plain, ref), (packed, got) = run(False), run(True)
    assert packed.head_w.is_mkldnn and not plain.head_w.is_mkldnn
    scale = float(ref.abs().max())
    torch.testing.assert_close(got, ref, atol=(2e-5 if wdt is None else 2e-2) * scale, rtol=0)
    assert torch.equal(LeanLlama.dense(packed.head_w), plain.head_w)
    for a, b in zip(packed.layers, plain.layers):
        for i in (1, 3, 6, 9):
            assert torch.equal(LeanLlama.dense(a[i]), b[i]), i
    with torch.no_grad():
        for p in model.model.layers[0].mlp.parameters():
            p.mul_(-2.0)
        packed.load(model)
    monkeypatch.setattr(decode, "PACK", False)
    fresh = LeanLlama(model, weight_dtype=wdt)
    assert torch.equal(LeanLlama.dense(packed.layers[0][6]), fresh.layers[0][6])
    assert torch.equal(LeanLlama.dense(packed.layers[0][9]), fresh.layers[0][9])


def test_lean_prefill_chunks_match_hf(trained):
    """Many prompts of very different lengths: prefill runs in several length-bucketed chunks."""
    model = trained[0]
    g = torch.Generator().manual_seed(2)
    lens = sorted(int(n) for n in torch.randint(1, 60, (24,), generator=g))
    seqs = [torch.randint(3, model.config.vocab_size, (n,), generator=g).tolist() for n in lens]
    ids, am = _left_pad(seqs)
    pos = (am.cumsum(-1) - 1).clamp(min=0)
    with torch.no_grad():
        ref = model(input_ids=ids, attention_mask=am, position_ids=pos).logits[:, -1]
    lean = LeanLlama(model)
    assert len(lean._prefill_chunks(lens)) > 1
    with torch.inference_mode():
        lean.start(len(seqs), ids.shape[1] + 1, ids.shape[1] + 2)
        got = lean.prefill(ids, am.bool(), pos, torch.arange(len(seqs)))
        torch.testing.assert_close(got, ref, atol=1e-4, rtol=0)
        # The cache columns left of each chunk are finite: one decode step stays exact.
        nxt = torch.randint(3, model.config.vocab_size, (len(seqs), 1), generator=g)
        got = lean.decode(nxt, am.sum(-1), ids.shape[1])
    with torch.no_grad():
        ids2, am2 = torch.cat([ids, nxt], 1), torch.cat([am, torch.ones_like(nxt)], 1)
        ref2 = model(input_ids=ids2, attention_mask=am2, position_ids=(am2.cumsum(-1) - 1).clamp(min=0)).logits
    torch.testing.assert_close(got, ref2[:, -1], atol=1e-4, rtol=0)


def test_weight_updates_are_seen(trained):
    """The fused lean weights are cached per model and rebuilt after an optimizer step."""
    model, tok, prompts = trained
    model = __import__("copy").deepcopy(model)
    before = generate(model, tok, prompts, greedy=True, max_new_tokens=8)
    with torch.no_grad():
        for p in model.model.layers[0].mlp.parameters():
            p.mul_(-3.0)  # in place, like an optimizer step
    after = generate(model, tok, prompts, greedy=True, max_new_tokens=8)
    ref = generate(model, tok, prompts, greedy=True, max_new_tokens=8, backend="hf")
    assert [r.completion_ids for r in after] == [r.completion_ids for r in ref]
    assert [r.completion_ids for r in after] != [r.completion_ids for r in before]


def test_backend_selection_reasons(trained):
    model = trained[0]
    assert select_backend(model, 64)[0].name == "lean"
    assert select_backend(model, 64, "hf")[0].name == "hf"
    bf16 = build_model("tiny", trained[1], dtype=torch.bfloat16)  # half weights run natively (test_half_precision)
    fwd, why = select_backend(bf16, 64)
    assert fwd.name == "lean" and fwd.dtype == torch.bfloat16 and "bfloat16 weights" in why
    fp64 = build_model("tiny", trained[1]).double()
    fwd, why = select_backend(fp64, 64)
    assert fwd.name == "hf" and "fp32, bf16 or fp16" in why
    with pytest.raises(ValueError, match="cannot run this model"):
        select_backend(fp64, 64, "lean")


# ------------------------------------------------------------------ bf16 rollout weights (rollout.dtype)


@pytest.fixture
def bf16_rollouts():
    from posttrain.rollout import engine

    engine.configure(dtype="bfloat16")
    yield
    engine.configure(dtype="float32")


@pytest.mark.parametrize("kind", ["tiny", "qwen2"])  # qwen2: q/k/v biases on the bf16 path
def test_bf16_weights_logits_within_bf16_rounding(kind, trained, small_llama):
    model = trained[0] if kind == "tiny" else small_llama(kind)
    V = model.config.vocab_size
    g = torch.Generator().manual_seed(4)
    ids, am = _left_pad([torch.randint(3, V, (n,), generator=g).tolist() for n in (6, 13, 9)])
    pos = (am.cumsum(-1) - 1).clamp(min=0)
    B, T = ids.shape
    nxt = torch.randint(3, V, (B, 1), generator=g)
    out = {}
    for name, wdt in (("fp32", None), ("bf16", torch.bfloat16)):
        lean = LeanLlama(model, weight_dtype=wdt)
        with torch.inference_mode():
            lean.start(B, T + 1, T + 4)
            first = lean.prefill(ids, am.bool(), pos, torch.arange(B))
            out[name] = torch.cat([first, lean.decode(nxt, am.sum(-1), T)])
        if wdt is not None:
            assert lean.head_w.dtype == lean.layers[0][1].dtype == torch.bfloat16
    ref, got = out["fp32"], out["bf16"]
    assert got.dtype == torch.float32  # the sampler reads fp32 logits
    err = (got - ref).abs().max() / ref.abs().max()
    # bf16 keeps 8 significant bits (relative rounding 2^-9 per operand): a few matmuls deep, the logits
    # stay within a few percent of their scale -- but they do differ (the weights really are bf16)
    assert 0 < err < 0.05, float(err)
    assert torch.corrcoef(torch.stack([got.flatten(), ref.flatten()]))[0, 1] > 0.999


def test_bf16_engine_is_selected_cached_and_refreshed(trained, bf16_rollouts):
    model, tok, prompts = trained
    model = __import__("copy").deepcopy(model)
    fwd, why = select_backend(model, 64)
    assert fwd.name == "lean" and fwd.weight_dtype == torch.bfloat16 and "weights bfloat16" in why
    assert select_backend(model, 64)[0] is fwd  # cached while the weights do not change
    assert select_backend(model, 64, dtype="float32")[0].weight_dtype == torch.float32  # another dtype: rebuilt
    assert "applies to the lean engine only" in select_backend(model, 64, "hf")[1]
    before = generate(model, tok, prompts, greedy=True, max_new_tokens=8)
    with torch.no_grad():
        for p in model.model.layers[0].mlp.parameters():
            p.mul_(-3.0)  # in place, like an optimizer step
    after = generate(model, tok, prompts, greedy=True, max_new_tokens=8)
    fresh = LeanLlama(model, weight_dtype=torch.bfloat16)
    assert select_backend(model, 64)[0] is not fresh
    dense = LeanLlama.dense
    torch.testing.assert_close(dense(select_backend(model, 64)[0].head_w), dense(fresh.head_w))  # refreshed
    torch.testing.assert_close(dense(select_backend(model, 64)[0].layers[0][6]), dense(fresh.layers[0][6]))
    assert [r.completion_ids for r in after] != [r.completion_ids for r in before]


def test_bf16_sampler_logprobs_close_to_the_fp32_policy(trained, bf16_rollouts):
    """What the trainers log as mismatch/kl: small but not zero."""
    model, tok, prompts = trained
    rollouts = generate(model, tok, prompts, n=4, max_new_tokens=16, seed=5)
    batch = collate_rollouts(rollouts, tok.pad_token_id)
    policy, _ = batched_logprobs(model, batch, micro_batch_size=8)
    mask = batch.completion_mask.bool()
    gap = (policy - batch.policy_logprobs)[mask]
    assert 0 < gap.abs().max() < 0.5 and gap.abs().mean() < 0.05, (float(gap.abs().max()), float(gap.abs().mean()))


def test_rollout_dtype_is_checked():
    from posttrain.config import ConfigError, resolve
    from posttrain.rollout import engine
    from posttrain.trainers.grpo import GRPOConfig

    with pytest.raises(ValueError, match="rollout dtype must be one of auto, float32, bfloat16"):
        engine.configure(dtype="float16")
    with pytest.raises(ConfigError, match="rollout.dtype"):
        resolve("tiny-math", "grpo", GRPOConfig, ["rollout.dtype=int8"])
    assert resolve("tiny-math", "grpo", GRPOConfig, ["rollout.dtype=bfloat16"]).rollout.dtype == "bfloat16"


@pytest.mark.parametrize("native", [True, False])
def test_rollout_dtype_auto_is_bf16_only_where_bf16_is_native(native, monkeypatch):
    from posttrain import runtime
    from posttrain.rollout import engine

    monkeypatch.setattr(runtime, "native_bf16", lambda: native)
    try:
        engine.configure(dtype="auto")
        assert engine._defaults["dtype"] == ("bfloat16" if native else "float32")
    finally:
        engine.configure()


# ------------------------------------------------------------------ greedy == model.generate


@pytest.mark.parametrize("backend", ["lean", "hf"])
def test_greedy_matches_hf_generate(trained, backend):
    model, tok, prompts = trained
    enc = tok(prompts, return_tensors="pt", padding=True)
    with torch.no_grad():
        out = model.generate(**enc, do_sample=False, max_new_tokens=20, pad_token_id=tok.pad_token_id,
                             eos_token_id=tok.eos_token_id, output_scores=True, return_dict_in_generate=True)
    top2 = torch.stack([s.topk(2, -1).values for s in out.scores], 1)  # (B, steps, 2)
    T = enc.input_ids.shape[1]
    rollouts = generate(model, tok, prompts, greedy=True, max_new_tokens=20, backend=backend)
    assert len({r.text for r in rollouts}) > 1  # a meaningful comparison: the prompts continue differently
    for i, r in enumerate(rollouts):
        ref = out.sequences[i, T:].tolist()
        n = len(r.completion_ids)
        margin = (top2[i, :n, 0] - top2[i, :n, 1]).min().item()
        assert margin > 1e-4, "near-tie in greedy path; pick other prompts"
        assert r.completion_ids == ref[:n], (prompts[i], r.text)
        if r.finish_reason == "eos":
            assert r.completion_ids[-1] == tok.eos_token_id and all(t == tok.pad_token_id for t in ref[n:])
        else:
            assert r.finish_reason == "length" and n == 20
        assert r.text == tok.decode(r.completion_ids, skip_special_tokens=True)
        assert r.logprobs == [0.0] * n  # greedy: the sampling distribution is a point mass


def test_top_k_1_is_greedy(trained):
    model, tok, prompts = trained
    a = generate(model, tok, prompts, greedy=True, max_new_tokens=12)
    b = generate(model, tok, prompts, top_k=1, temperature=1.3, max_new_tokens=12, seed=5)
    assert [r.completion_ids for r in a] == [r.completion_ids for r in b]


# ------------------------------------------------------------------ log-probs


def test_sampling_logprobs_match_recomputed(trained):
    model, tok, prompts = trained
    for params in (dict(temperature=1.0), dict(temperature=0.7), dict(temperature=0.9, top_p=0.8)):
        rollouts = generate(model, tok, prompts, n=2, max_new_tokens=16, seed=3, **params)
        batch = collate_rollouts(rollouts, tok.pad_token_id)
        policy, _ = batched_logprobs(model, batch, micro_batch_size=4)
        torch.testing.assert_close(policy * batch.completion_mask, batch.policy_logprobs, atol=1e-4, rtol=0)
        if "top_p" not in params:  # unfiltered: the sampler's distribution is softmax(logits / T)
            sampled, _ = batched_logprobs(model, batch, micro_batch_size=4, temperature=params["temperature"])
            torch.testing.assert_close(sampled * batch.completion_mask, batch.logprobs, atol=1e-4, rtol=0)
        else:  # the nucleus distribution, recomputed independently of the sampler
            expected = _nucleus_logprobs(model, batch, params["temperature"], params["top_p"])
            torch.testing.assert_close(expected, batch.logprobs, atol=1e-4, rtol=0)


def _nucleus_logprobs(model, batch, temperature: float, top_p: float) -> torch.Tensor:
    """log q(token) where q is softmax(logits / T) restricted to the nucleus (tokens sorted by probability, kept
    while the mass strictly before them is < top_p) and renormalised: the distribution top-p sampling draws
    from, computed here in float64 from a plain HF forward, not from the sampler's code. (B, T), 0 off-mask."""
    am = batch.attention_mask
    with torch.no_grad():
        logits = model(input_ids=batch.input_ids, attention_mask=am,
                       position_ids=(am.long().cumsum(-1) - 1).clamp(min=0)).logits.double()  # (B, T, V)
    probs = torch.softmax(logits[:, :-1] / temperature, -1)  # (B, T-1, V): next-token distributions
    sorted_p, order = probs.sort(-1, descending=True)
    keep = torch.zeros_like(probs, dtype=torch.bool).scatter(-1, order, (sorted_p.cumsum(-1) - sorted_p) < top_p)
    kept = probs * keep
    q = kept.gather(-1, batch.input_ids[:, 1:, None])[..., 0] / kept.sum(-1)  # (B, T-1)
    out = torch.zeros(batch.input_ids.shape, dtype=torch.float64)
    out[:, 1:] = q.log()
    return torch.where(batch.completion_mask.bool(), out, torch.zeros_like(out)).float()


# ------------------------------------------------------------------ finishing: EOS, stop strings, length


def test_eos_and_stop_strings(trained):
    model, tok, prompts = trained
    base = generate(model, tok, prompts, greedy=True, max_new_tokens=24)
    # EOS: declare a token the greedy path emits to be an EOS (via the generation config).
    r0 = next(r for r in base if len(set(r.completion_ids)) > 3)
    k = 3
    eos_like = r0.completion_ids[k]
    k = r0.completion_ids.index(eos_like)
    old = model.generation_config.eos_token_id
    model.generation_config.eos_token_id = [tok.eos_token_id, eos_like]
    try:
        got = generate(model, tok, [r0.prompt_ids], greedy=True, max_new_tokens=24)[0]
    finally:
        model.generation_config.eos_token_id = old
    assert got.finish_reason == "eos" and got.completion_ids == r0.completion_ids[:k + 1]
    assert got.completion_mask == [1] * (k + 1)

    # Stop strings: cut at the first occurrence, excluded from text by default, included on request.
    text = r0.text
    stop = text[6:9]
    assert stop and stop in text
    at = text.index(stop)
    for include in (False, True):
        r = generate(model, tok, [r0.prompt_ids], greedy=True, max_new_tokens=24, stop=[stop, "\x00never"],
                     include_stop=include)[0]
        assert r.finish_reason == "stop"
        assert r.text == (text[:at + len(stop)] if include else text[:at])
        assert r.completion_ids == r0.completion_ids[:len(r.completion_ids)]
        full = tok.decode(r.completion_ids, skip_special_tokens=True)
        assert stop in full and stop not in tok.decode(r.completion_ids[:-1], skip_special_tokens=True)
    # Rows without the stop string run to the length limit; the batch mask covers exactly the tokens.
    many = generate(model, tok, prompts, greedy=True, max_new_tokens=24, stop=[stop])
    batch = collate_rollouts(many, tok.pad_token_id)
    for i, r in enumerate(many):
        assert r.finish_reason in ("stop", "length", "eos")
        assert int(batch.completion_mask[i].sum()) == len(r.completion_ids)
        assert batch.completion_ids[i, :len(r.completion_ids)].tolist() == r.completion_ids


def test_context_limit_clips_completion():
    tok = train_tokenizer(["a b c d e f g h"] * 20, vocab_size=64)
    model = build_model("tiny", tok, seed=0)  # context 512
    r = generate(model, tok, [[5] * 509], max_new_tokens=10, ignore_eos=True)[0]
    assert r.finish_reason == "length" and len(r.completion_ids) == 3
    with pytest.raises(ValueError, match="context is 512"):
        generate(model, tok, [[5] * 512], max_new_tokens=1)


# ------------------------------------------------------------------ seeding and batch invariance


def test_same_seed_same_samples_and_batch_invariance(trained):
    model, tok, prompts = trained
    kw = dict(n=3, max_new_tokens=16, temperature=1.0, seed=11)
    a = generate(model, tok, prompts, **kw)
    b = generate(model, tok, prompts, **kw)
    assert [r.completion_ids for r in a] == [r.completion_ids for r in b]
    c = generate(model, tok, prompts, **{**kw, "seed": 12})
    assert [r.completion_ids for r in a] != [r.completion_ids for r in c]
    # Another batch composition: a subset of prompts, reversed, keyed by their original index, tiny
    # micro-batches (one row each), fewer samples, through the HF forward.
    sub = [4, 1, 0]
    for extra in (dict(max_batch_tokens=1), dict(backend="hf"), dict(n=2), dict(max_batch_tokens=300)):
        d = generate(model, tok, [prompts[i] for i in sub], prompt_keys=sub, **{**kw, **extra})
        for r in d:
            ref = a[sub[r.prompt_index] * 3 + r.sample_index]
            assert r.completion_ids == ref.completion_ids
            torch.testing.assert_close(torch.tensor(r.policy_logprobs), torch.tensor(ref.policy_logprobs),
                                       atol=1e-4, rtol=0)


def test_finished_rows_dropped_do_not_change_others(trained):
    """Rows end at different steps (EOS = a frequent token): each row equals its own solo run."""
    model, tok, prompts = trained
    frequent = tok(" ")["input_ids"][0]
    old = model.generation_config.eos_token_id
    model.generation_config.eos_token_id = [tok.eos_token_id, frequent]
    try:
        many = generate(model, tok, prompts * 3, max_new_tokens=20, seed=2, temperature=1.2)
        assert len({len(r.completion_ids) for r in many}) > 2
        many_hf = generate(model, tok, prompts * 3, max_new_tokens=20, seed=2, temperature=1.2, backend="hf")
        assert [r.completion_ids for r in many_hf] == [r.completion_ids for r in many]
        for i in (0, 7, 13):
            solo = generate(model, tok, [prompts[i % len(prompts)]], prompt_keys=[i], max_new_tokens=20, seed=2,
                            temperature=1.2)[0]
            assert solo.completion_ids == many[i].completion_ids and solo.finish_reason == many[i].finish_reason
    finally:
        model.generation_config.eos_token_id = old


# ------------------------------------------------------------------ top-k / top-p distribution


def test_top_k_top_p_distribution():
    probs = torch.tensor([0.4, 0.25, 0.15, 0.1, 0.06, 0.04])
    logits = probs.log().expand(40000, -1).contiguous()
    u = row_uniforms(7, torch.arange(40000), torch.zeros(40000, dtype=torch.long), 1)  # (R, 1)
    cases = [
        (dict(), probs),
        (dict(top_k=3), torch.tensor([0.4, 0.25, 0.15, 0, 0, 0]) / 0.8),
        (dict(top_p=0.7), torch.tensor([0.4, 0.25, 0.15, 0, 0, 0]) / 0.8),  # mass before 3rd = 0.65 < 0.7
        (dict(top_p=0.65), torch.tensor([0.4, 0.25, 0, 0, 0, 0]) / 0.65),
        (dict(top_k=4, top_p=0.5), torch.tensor([0.4, 0.25, 0, 0, 0, 0]) / 0.65),
        (dict(temperature=0.5), probs ** 2 / (probs ** 2).sum()),
    ]
    for kw, expected in cases:
        tok, logp, policy = Sampler(SamplingParams(**kw), 6)(logits, u)
        freq = torch.bincount(tok.view(-1), minlength=6).float() / len(tok)
        torch.testing.assert_close(freq, expected, atol=0.01, rtol=0, msg=str(kw))
        assert (freq[expected == 0] == 0).all(), kw
        torch.testing.assert_close(logp.view(-1), expected.log()[tok.view(-1)], atol=1e-5, rtol=0)
        torch.testing.assert_close(policy.view(-1), probs.log()[tok.view(-1)], atol=1e-5, rtol=0)


def test_uniforms_are_uniform_and_independent():
    u = row_uniforms(0, torch.arange(2000), torch.arange(2000) % 4, 50)  # (2000, 50)
    assert 0 <= u.min() and u.max() < 1
    assert abs(u.mean().item() - 0.5) < 0.01 and abs(u.var().item() - 1 / 12) < 0.005
    hist = torch.histc(u, bins=10, min=0, max=1) / u.numel()
    assert (hist - 0.1).abs().max() < 0.01
    corr = torch.corrcoef(torch.stack([u[:, :-1].reshape(-1), u[:, 1:].reshape(-1)]))[0, 1]
    assert abs(corr.item()) < 0.02
    assert not torch.equal(row_uniforms(1, torch.arange(5), torch.zeros(5), 3), row_uniforms(0, torch.arange(5),
                                                                                            torch.zeros(5), 3))


# ------------------------------------------------------------------ errors


@pytest.mark.parametrize("prompts, kw, match", [
    ([""], {}, "prompt 0 is empty"),
    ([[]], {}, "prompt 0 is empty"),
    (["hi", [3] * 600], {}, "prompt 1 has 600 tokens but the model's context is 512"),
    (["hi"], dict(n=0), "n must be"),
    (["hi"], dict(temperature=-1.0), "temperature"),
    (["hi"], dict(top_p=0.0), "top_p"),
    (["hi"], dict(top_p=1.5), "top_p"),
    (["hi"], dict(top_k=-2), "top_k"),
    (["hi"], dict(max_new_tokens=0), "max_new_tokens"),
    (["hi"], dict(stop="\n"), "stop"),
    (["hi"], dict(nucleus=0.9), "unknown sampling option"),
    ([[10 ** 6]], {}, "outside"),
    ("hi", {}, "list of strings"),
])
def test_bad_inputs_raise_one_line_errors(trained, prompts, kw, match):
    model, tok, _ = trained
    with pytest.raises(ValueError, match=match) as e:
        generate(model, tok, prompts, **kw)
    assert "\n" not in str(e.value)


def test_empty_prompt_list_returns_nothing(trained):
    assert generate(trained[0], trained[1], []) == []


# ------------------------------------------------------------------ records: collate, save / load


@pytest.mark.parametrize("suffix", [".jsonl", ".parquet"])
def test_save_load_round_trip(trained, tmp_path, suffix):
    model, tok, prompts = trained
    rollouts = generate(model, tok, prompts[:3], n=2, max_new_tokens=8, seed=1)
    rollouts[0].reward = 1.0
    rollouts[1].extras = {"verifier": "math", "details": {"answer": "4", "ok": True}}
    rollouts[2].completion_mask = [0] * len(rollouts[2].completion_ids)
    path = save_rollouts(rollouts, tmp_path / f"r{suffix}")
    back = load_rollouts(path)
    assert back == rollouts
    if suffix == ".jsonl":
        row = json.loads(path.read_text().splitlines()[1])
        assert json.loads(row["extras_json"])["details"]["ok"] is True


def test_collate_layout(trained):
    model, tok, prompts = trained
    rollouts = generate(model, tok, prompts[:3], max_new_tokens=6, seed=0)
    for r in rollouts:
        r.reward = float(len(r.text))
    b = collate_rollouts(rollouts, tok.pad_token_id)
    P = max(len(r.prompt_ids) for r in rollouts)
    assert b.prompt_length == P and b.input_ids.shape[1] == P + max(len(r.completion_ids) for r in rollouts)
    for i, r in enumerate(rollouts):
        assert b.input_ids[i, P - len(r.prompt_ids):P].tolist() == r.prompt_ids
        assert b.attention_mask[i].sum() == len(r.prompt_ids) + len(r.completion_ids)
        assert b.logprobs[i, P:P + len(r.logprobs)].tolist() == pytest.approx(r.logprobs)
    assert b.rewards.tolist() == [float(len(r.text)) for r in rollouts]
    assert len(b.select([0, 2])) == 2
    with pytest.raises(ValueError, match="same length"):
        Rollout([1], [2, 3], [0.0], [0.0], "length", "x", 0, 0)


def test_lora_model_runs_the_lean_path_with_adapters_fused(trained):
    """A peft LoRA model: the lean path fuses base + adapter deltas (logits equal the peft forward's),
    sees adapter updates and `disable_adapter()` (the reference), and samples the same tokens and
    log-probs as the HF forward of the same LoRA model. DoRA is refused with a reason."""
    peft = pytest.importorskip("peft")
    from posttrain.models import reference_view

    model, tok, prompts = trained
    lora = peft.get_peft_model(__import__("copy").deepcopy(model),
                               peft.LoraConfig(r=4, lora_alpha=8, target_modules=["q_proj", "v_proj", "down_proj"],
                                               lora_dropout=0.0))
    fwd, why = select_backend(lora, 64)
    assert fwd.name == "lean" and "LoRA fused" in why
    # A fresh adapter (B = 0) is the identity: the base model's greedy text.
    a = generate(model, tok, prompts, greedy=True, max_new_tokens=10)
    assert [r.completion_ids for r in generate(lora, tok, prompts, greedy=True, max_new_tokens=10)] == \
        [r.completion_ids for r in a]
    with torch.no_grad():  # a trained-looking adapter: B != 0 (in place, as an optimizer step would)
        for name, prm in lora.named_parameters():
            if "lora_B" in name:
                prm.normal_(0, 0.2)
    lean = generate(lora, tok, prompts, n=2, max_new_tokens=12, seed=3)
    hf = generate(lora, tok, prompts, n=2, max_new_tokens=12, seed=3, backend="hf")
    assert [r.completion_ids for r in lean] == [r.completion_ids for r in hf]
    assert [r.completion_ids for r in lean] != [r.completion_ids for r in
                                                generate(model, tok, prompts, n=2, max_new_tokens=12, seed=3)]
    torch.testing.assert_close(torch.tensor([x for r in lean for x in r.policy_logprobs]),
                               torch.tensor([x for r in hf for x in r.policy_logprobs]), atol=1e-4, rtol=0)
    batch = collate_rollouts(lean, tok.pad_token_id)
    lp, _ = batched_logprobs(lora, batch, micro_batch_size=3)
    torch.testing.assert_close(lp * batch.completion_mask, batch.policy_logprobs, atol=1e-4, rtol=0)
    # Adapters off = the base model, in the engine and through reference_view (no weight copy).
    with lora.disable_adapter():
        off = generate(lora, tok, prompts, greedy=True, max_new_tokens=10)
    assert [r.completion_ids for r in off] == [r.completion_ids for r in a]
    ref_lp, _ = batched_logprobs(reference_view(lora), batch, micro_batch_size=3)
    base_lp, _ = batched_logprobs(model, batch, micro_batch_size=3)
    # the same math in another summation order (PEFT's layers with adapters off vs the plain model): fp32 rounding
    # of log-probs of magnitude ~3 reaches 2e-5 on some machines, so the bound is the suite's usual 1e-4
    torch.testing.assert_close(ref_lp, base_lp, atol=1e-4, rtol=0)
    dora = peft.get_peft_model(__import__("copy").deepcopy(model),
                               peft.LoraConfig(r=4, target_modules=["q_proj"], use_dora=True))
    fwd, why = select_backend(dora, 64)
    assert fwd.name == "hf" and "variant" in why


def test_token_id_prompts_without_tokenizer(trained):
    model, tok, prompts = trained
    ids = [tok(p)["input_ids"] for p in prompts[:2]]
    a = generate(model, None, ids, greedy=True, max_new_tokens=5)
    b = generate(model, tok, prompts[:2], greedy=True, max_new_tokens=5)
    assert [r.completion_ids for r in a] == [r.completion_ids for r in b] and a[0].text == "" and a[0].prompt is None
    with pytest.raises(ValueError, match="need a tokenizer"):
        generate(model, None, ids, stop=["x"])
    with pytest.raises(ValueError, match="no tokenizer"):
        generate(model, None, ["text prompt"])
