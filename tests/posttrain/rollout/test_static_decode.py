"""The static-shape decode step (`LeanLlama.start(..., static=True)` / `step()`, the engine's path on CUDA) and the
every-k-steps EOS check, run eagerly on CPU against the default path: same tokens, finish reasons and log-probs
(fp32 rounding), with left-padded prompts of different lengths, rows that finish at different steps (EOS) and
rows with different length limits (context clipping). The CUDA tests at the end (graph capture and replay) skip
without a GPU."""
from __future__ import annotations

import copy
from collections import Counter

import pytest
import torch

from posttrain.lean import decode
from posttrain.rollout import LeanLlama, engine, generate

pytestmark = pytest.mark.usefixtures("one_thread")  # correctness tests (tests/conftest.py)

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")  # (besides `cuda`)


def _steps(lean: LeanLlama, static: bool, steps: int = 5):
    """Prefill 3 left-padded prompts (lengths 5, 11, 8), then `steps` decode steps -> logits (B, 1 + steps, V)."""
    dev = lean.device
    g = torch.Generator().manual_seed(1)
    seqs = [torch.randint(3, 97, (n,), generator=g).tolist() for n in (5, 11, 8)]
    B, T = len(seqs), max(map(len, seqs))
    ids = torch.zeros(B, T, dtype=torch.long)
    am = torch.zeros(B, T, dtype=torch.long)
    for i, s in enumerate(seqs):
        ids[i, T - len(s):] = torch.tensor(s)
        am[i, T - len(s):] = 1
    nxt = torch.randint(3, 97, (B, steps), generator=g).to(dev)
    ids, am = ids.to(dev), am.to(dev)
    pos = (am.cumsum(-1) - 1).clamp(min=0)
    out = []
    with torch.inference_mode():
        lean.start(B, T + steps, T + steps + 4, static=static)
        out.append(lean.prefill(ids, am.bool(), pos, torch.arange(B, device=dev)).float())
        p = am.sum(-1)
        if static:
            lean.st.pos.copy_(p)
            lean.st.col.fill_(T)
        for s in range(steps):
            if static:
                lean.st.tok.copy_(nxt[:, s:s + 1])
                out.append(lean.step().clone())
                lean.st.pos.add_(1)
                lean.st.col.add_(1)
            else:
                out.append(lean.decode(nxt[:, s:s + 1], p + s, T + s).float())
        lean.release()
    return torch.stack(out, 1)


@pytest.mark.parametrize("packed", [True, False], ids=["packed", "plain"])
@pytest.mark.parametrize("kind", ["llama-gqa", "qwen2"])
def test_static_step_equals_decode(kind, packed, monkeypatch, small_llama):
    monkeypatch.setattr(decode, "PACK", packed)
    monkeypatch.setattr(decode, "PACK_MIN_HIDDEN", 0)
    lean = LeanLlama(small_llama(kind))
    a, b = _steps(lean, static=False), _steps(lean, static=True)
    assert lean.cols % decode.STATIC_COLS == 0  # the static width is rounded up: masked, never-written columns
    torch.testing.assert_close(b, a, atol=1e-5 * float(a.abs().max()), rtol=0)


def _eos_model(trained_lm):
    """A copy of the trained model whose EOS set includes a token the sampled text uses often (rows end at
    different steps) and whose context is short (long prompts get a clipped length limit)."""
    model, tok, prompts = trained_lm
    model = copy.deepcopy(model)
    base = generate(model, tok, prompts, n=2, max_new_tokens=20, seed=1, ignore_eos=True)
    counts = Counter(t for r in base for t in set(r.completion_ids[1:]))
    eos_like = max(counts, key=lambda t: (counts[t] < len(base), counts[t]))  # in most rows, not all
    model.generation_config.eos_token_id = [tok.eos_token_id, eos_like]
    model.config.max_position_embeddings = max(len(r.prompt_ids) for r in base) + 12
    return model, tok, prompts


def _run(model, tok, prompts, **kw):
    return generate(model, tok, prompts, n=3, max_new_tokens=20, seed=7, temperature=0.9, max_batch_tokens=300, **kw)


def _same(a, b, exact: bool):
    assert [r.completion_ids for r in a] == [r.completion_ids for r in b]
    assert [r.finish_reason for r in a] == [r.finish_reason for r in b]
    for x, y in zip(a, b):
        if exact:
            assert x.logprobs == y.logprobs and x.policy_logprobs == y.policy_logprobs
        else:
            torch.testing.assert_close(torch.tensor(x.logprobs), torch.tensor(y.logprobs), atol=1e-5, rtol=0)
            torch.testing.assert_close(torch.tensor(x.policy_logprobs), torch.tensor(y.policy_logprobs), atol=1e-5,
                                       rtol=0)


def test_static_engine_path_equals_the_default_path(trained_lm, monkeypatch):
    model, tok, prompts = _eos_model(trained_lm)
    ref = _run(model, tok, prompts)
    assert {"eos", "length"} <= {r.finish_reason for r in ref}
    assert len({len(r.completion_ids) for r in ref if r.finish_reason == "eos"}) >= 3  # EOS at different steps
    ctx = model.config.max_position_embeddings
    assert any(len(r.completion_ids) < 20 and r.finish_reason == "length" and len(r.prompt_ids) + 20 > ctx
               for r in ref)  # a clipped limit
    monkeypatch.setattr(engine, "STATIC_DECODE", True)
    got = _run(model, tok, prompts)
    _same(got, ref, exact=False)
    greedy_ref = generate(model, tok, prompts, greedy=True, max_new_tokens=20)
    monkeypatch.setattr(engine, "STATIC_DECODE", False)
    assert [r.completion_ids for r in generate(model, tok, prompts, greedy=True, max_new_tokens=20)] == \
        [r.completion_ids for r in greedy_ref]


@pytest.mark.parametrize("every", [3, 8])
@pytest.mark.parametrize("static", [False, True], ids=["compacting", "static"])
def test_eos_checked_every_k_steps_equals_every_step(trained_lm, monkeypatch, static, every):
    """Deferred EOS checks find each row's first EOS in the window from the recorded tokens: the same lengths,
    reasons and log-probs as checking every step (bit-identical on the static path, whose batch shape never
    changes; within fp32 rounding when compaction happens at other steps)."""
    model, tok, prompts = _eos_model(trained_lm)
    monkeypatch.setattr(engine, "STATIC_DECODE", static)
    monkeypatch.setattr(engine, "EOS_CHECK_EVERY", 1)
    ref = _run(model, tok, prompts)
    seen = []
    monkeypatch.setattr(engine, "EOS_CHECK_EVERY", every)
    got = _run(model, tok, prompts, progress=lambda done, total: seen.append(done))
    _same(got, ref, exact=static)
    assert seen[-1] == len(ref) and seen == sorted(seen)
    # with stop strings EOS is checked every step (the text check decodes every step anyway): still the same
    stop = generate(model, tok, prompts, n=2, max_new_tokens=16, seed=2, stop=["s a"])
    monkeypatch.setattr(engine, "EOS_CHECK_EVERY", 1)
    _same(stop, generate(model, tok, prompts, n=2, max_new_tokens=16, seed=2, stop=["s a"]), exact=True)


# ----------------------------------------------------------------------------- CUDA (skipped without a GPU)


@pytest.mark.cuda
@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16], ids=["fp32", "bf16"])
def test_cuda_graph_replay_equals_eager_static_steps(dtype, monkeypatch, small_llama):
    model = small_llama("llama-gqa", "cuda", dtype)
    graphed = LeanLlama(model)
    a = _steps(graphed, static=True)
    st = next(iter(graphed._states.values()))
    assert st.graph is not None, "capture failed (see the logged warning)"
    monkeypatch.setattr(decode, "CUDA_GRAPHS", False)
    eager = LeanLlama(model)
    b = _steps(eager, static=True)
    assert not eager._states
    torch.testing.assert_close(a, b, atol=1e-6 * float(b.abs().max()), rtol=0)
    c = _steps(LeanLlama(model), static=False)  # the compacting path's decode
    tol = 1e-5 if dtype == torch.float32 else 2.0 ** -6
    torch.testing.assert_close(a, c, atol=tol * float(c.abs().max()), rtol=0)
    # weights refreshed in place (an optimizer step + `load`): the same graph replays with the new weights
    with torch.no_grad():
        model.model.layers[0].mlp.down_proj.weight.mul_(-2.0)
        model.lm_head.weight.add_(0.1)
    graphed.load(model)
    monkeypatch.setattr(decode, "CUDA_GRAPHS", True)
    a2 = _steps(graphed, static=True)
    assert next(iter(graphed._states.values())) is st  # reused, not recaptured
    monkeypatch.setattr(decode, "CUDA_GRAPHS", False)
    b2 = _steps(LeanLlama(model), static=True)
    torch.testing.assert_close(a2, b2, atol=1e-6 * float(b2.abs().max()), rtol=0)
    assert not torch.allclose(a2, a)


@pytest.mark.cuda
@needs_cuda
def test_cuda_generate_with_graphs_equals_the_per_step_path(trained_lm, monkeypatch):
    model, tok, prompts = _eos_model(trained_lm)
    model = model.cuda()
    got = _run(model, tok, prompts)  # static step, CUDA graph, EOS every EOS_CHECK_CUDA steps
    fwd = engine.select_backend(model, 64)[0]
    assert fwd.name == "lean" and any(s.graph is not None for s in fwd._states.values())
    monkeypatch.setattr(engine, "STATIC_DECODE", False)
    monkeypatch.setattr(engine, "EOS_CHECK_EVERY", 1)
    _same(got, _run(model, tok, prompts), exact=False)
