"""posttrain.lean.train: the lean training forward equals the HF forward (logits and every parameter's
gradient) on padded batches, sequence_logprobs gives the same numbers with the switch on and off, and
unsupported models fall back to the HF forward.

Tolerances (fp32): logits atol 1e-5; log-probs atol 1e-5 + rtol 2e-6 (values up to ~20); gradients rtol 1e-4 with atol 1e-5 * max|grad|
of that parameter (the two paths sum the same terms in a different order)."""
from __future__ import annotations

import importlib

import pytest
import torch
from torch import nn

from posttrain.lean import support
from posttrain.lean import train as lean_train
from posttrain.lean.support import lean_support
from posttrain.logprobs import position_ids_from_mask, sequence_logprobs

V = 97


pytestmark = pytest.mark.usefixtures("one_thread")  # correctness tests (tests/conftest.py)


_FAMILIES = {  # class-name prefix and the family's own defaults
    "llama": ("Llama", dict(num_key_value_heads=4, tie_word_embeddings=True)),
    "qwen2": ("Qwen2", dict(num_key_value_heads=2, tie_word_embeddings=False)),
    "mistral": ("Mistral", dict(num_key_value_heads=2, sliding_window=None)),
}


def _build(family: str, head: str = "ForCausalLM", **kw):
    """A small seeded model of `family` with head `ForCausalLM` or `ForSequenceClassification` (one label),
    perturbed (`_perturb`); keyword arguments override the config."""
    import transformers

    prefix, defaults = _FAMILIES[family]
    cfg = dict(vocab_size=V, hidden_size=64, intermediate_size=96, num_hidden_layers=2, num_attention_heads=4,
               max_position_embeddings=128, pad_token_id=0, **defaults)
    if head == "ForSequenceClassification":
        cfg["num_labels"] = 1
    cfg.update(kw)
    torch.manual_seed(0)
    config = getattr(transformers, f"{prefix}Config")(**cfg)
    return _perturb(getattr(transformers, f"{prefix}{head}")(config))


def _llama(**kw):
    return _build("llama", **kw)


def _qwen2(**kw):
    return _build("qwen2", **kw)


def _mistral():
    return _build("mistral")


def _perturb(model):
    """Random norm weights and biases (not the init's ones/zeros) and larger logits (causal LMs), so every parameter's
    gradient path is exercised; fp32, eval mode."""
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.dim() == 1:
                p.copy_(1.0 + 0.3 * torch.randn(p.shape, generator=g) if "norm" in name
                        else 0.1 * torch.randn(p.shape, generator=g))
        if hasattr(model, "lm_head"):
            model.lm_head.weight.mul_(10)
    return model.float().eval()


MODELS = {
    "llama-mha-tied": lambda: _llama(),
    "llama-gqa-untied": lambda: _llama(num_key_value_heads=2, tie_word_embeddings=False),
    "llama-biases": lambda: _llama(attention_bias=True, mlp_bias=True),
    "qwen2-gqa-bias": lambda: _qwen2(),
    "qwen2-tied": lambda: _qwen2(tie_word_embeddings=True, num_key_value_heads=4),
    "mistral": _mistral,
    "llama-yarn-rope": lambda: _llama(rope_parameters={"rope_type": "yarn", "factor": 2.0, "rope_theta": 10000.0,
                                                       "original_max_position_embeddings": 64}),  # attention_scaling != 1
}


def _batch(padding: str, B=4, T=13, seed=0):
    """(input_ids, attention_mask, completion_mask): left-padded prompts, right-padded completions, or both."""
    g = torch.Generator().manual_seed(seed)
    ids = torch.randint(3, V, (B, T), generator=g)
    am = torch.ones(B, T, dtype=torch.long)
    for i in range(B):
        if padding in ("left", "both"):
            am[i, :i] = 0  # row i: i leading pads
        if padding in ("right", "both"):
            am[i, T - (B - 1 - i):] = 0  # row i: B-1-i trailing pads
    ids = ids * am
    cm = am.clone()
    cm[:, :5] = 0  # a prompt of 5 columns
    return ids, am, cm


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("padding", ["none", "left", "right", "both"])
def test_logits_and_gradients_equal_hf(name, padding):
    model = MODELS[name]()
    ok, why = lean_support(model, 13, mode="train")
    assert ok, why
    ids, am, cm = _batch(padding)
    if padding != "none":
        assert not bool(am.all())
    pos = position_ids_from_mask(am)
    keep = 9
    real = am[:, -keep:].bool()  # (B, keep)

    def loss_of(logits):  # sum of log-probs of the next real tokens over the kept columns
        lp = torch.log_softmax(logits[:, :-1], -1).gather(-1, ids[:, -keep + 1:, None]).squeeze(-1)
        return (lp * (am[:, -keep + 1:] * am[:, -keep:-1])).sum()

    ref = model(input_ids=ids, attention_mask=am, position_ids=pos, logits_to_keep=keep).logits
    ref_grads = torch.autograd.grad(loss_of(ref), list(model.parameters()))
    out = lean_train.lean_forward(model, ids, am, pos, keep)
    assert out.dtype == torch.float32 and out.shape == ref.shape
    torch.testing.assert_close(out[real], ref[real], atol=1e-5, rtol=0)
    grads = torch.autograd.grad(loss_of(out), list(model.parameters()))
    for (pname, _), g, r in zip(model.named_parameters(), grads, ref_grads):
        assert r.abs().max() > 0, pname
        torch.testing.assert_close(g, r, rtol=1e-4, atol=1e-5 * float(r.abs().max()), msg=lambda m: f"{pname}: {m}")


def _run(model, ids, am, cm, enabled, **kw):
    before = support.ENABLED
    support.ENABLED = enabled
    try:
        model.zero_grad(set_to_none=True)
        lp, ent = sequence_logprobs(model, ids, am, cm, **kw)
        (lp.sum() * 0.7).backward()
        return lp.detach(), ent, {n: p.grad.clone() for n, p in model.named_parameters()}
    finally:
        support.ENABLED = before


@pytest.mark.parametrize("name", ["llama-mha-tied", "qwen2-gqa-bias"])
@pytest.mark.parametrize("temperature,entropy", [(1.0, False), (0.7, True)])
def test_sequence_logprobs_switch_on_equals_off(name, temperature, entropy, monkeypatch):
    model = MODELS[name]()
    ids, am, cm = _batch("both")
    calls = []
    real_forward = lean_train.lean_last_layer
    monkeypatch.setattr(lean_train, "lean_last_layer", lambda *a, **k: calls.append(1) or real_forward(*a, **k))
    kw = dict(temperature=temperature, return_entropy=entropy, entropy_grad=False)
    lp0, e0, g0 = _run(model, ids, am, cm, False, **kw)
    assert not calls
    lp1, e1, g1 = _run(model, ids, am, cm, True, **kw)
    assert calls, "the lean path was not taken"
    torch.testing.assert_close(lp1, lp0, atol=1e-5, rtol=2e-6)
    assert bool((lp1[cm == 0] == 0).all())
    if entropy:
        torch.testing.assert_close(e1, e0, atol=1e-5, rtol=2e-6)
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)
    # entropy with its gradient (PPO's entropy bonus): the loss is log-probs + entropy
    def run_ent(enabled):
        before = support.ENABLED
        support.ENABLED = enabled
        try:
            model.zero_grad(set_to_none=True)
            lp, ent = sequence_logprobs(model, ids, am, cm, temperature=temperature, return_entropy=True)
            (lp.sum() + 0.3 * ent.sum()).backward()
            return lp.detach(), ent.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}
        finally:
            support.ENABLED = before

    calls.clear()
    lp2, e2, g2 = run_ent(True)
    assert calls
    lp4, e4, g4 = run_ent(False)
    torch.testing.assert_close(lp2, lp4, atol=1e-5, rtol=2e-6)
    torch.testing.assert_close(e2, e4, atol=1e-5, rtol=2e-6)
    for n in g4:
        torch.testing.assert_close(g2[n], g4[n], rtol=1e-4, atol=1e-5 * float(g4[n].abs().max()), msg=n)
    calls.clear()
    monkeypatch.setattr(support, "ENABLED", True)
    with torch.no_grad():  # and under no_grad (reference / old log-probs) the lean path runs too
        lp3, _ = sequence_logprobs(model, ids, am, cm, temperature=temperature)
    assert calls
    torch.testing.assert_close(lp3, lp0, atol=1e-5, rtol=2e-6)


def test_the_head_runs_only_on_the_scored_columns(monkeypatch):
    """Padding and the prompt columns of rows with longer prompts never reach the (vocabulary-wide) head; the
    numbers are the ones above (switch on equals off)."""
    model = MODELS["llama-mha-tied"]()
    ids, am, cm = _batch("both")
    cm[1, 5:8] = 0  # row 1's prompt is 3 columns longer
    rows = []
    real_head = lean_train.lean_token_logprobs
    monkeypatch.setattr(lean_train, "lean_token_logprobs",
                        lambda m, x, t, *a, **k: rows.append(t.numel()) or real_head(m, x, t, *a, **k))
    lp1, _, g1 = _run(model, ids, am, cm, True)
    assert rows == [int(cm[:, 1:].sum())] and rows[0] < cm[:, 5:].numel()
    lp0, _, g0 = _run(model, ids, am, cm, False)
    torch.testing.assert_close(lp1, lp0, atol=1e-5, rtol=2e-6)
    assert bool((lp1[cm == 0] == 0).all())
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)


def test_completion_logits_are_the_scored_columns_distributions_on_both_paths():
    """completion_logits: one row per scored column (row-major), the full logits of the model at that column's
    prediction, lean and HF paths equal; scatter_scored puts per-token values back with zeros elsewhere."""
    from posttrain.logprobs import completion_logits, scatter_scored

    model = MODELS["qwen2-gqa-bias"]()
    ids, am, cm = _batch("both")
    cm[1, 5:8] = 0
    outs = {}
    for enabled in (True, False):
        before = support.ENABLED
        support.ENABLED = enabled
        try:
            outs[enabled] = completion_logits(model, ids, am, cm, temperature=0.7)
        finally:
            support.ENABLED = before
    (lg, index, c), (lg0, index0, c0) = outs[True], outs[False]
    assert c == c0 == 5 and torch.equal(index, index0) and lg.shape == (int(cm.sum()), V)
    torch.testing.assert_close(lg, lg0, atol=1e-5, rtol=0)
    full = model(input_ids=ids, attention_mask=am, position_ids=position_ids_from_mask(am)).logits / 0.7
    rows, cols = index // (ids.shape[1] - c), c + index % (ids.shape[1] - c)
    assert bool(cm[rows, cols].all())
    torch.testing.assert_close(lg, full[rows, cols - 1], atol=1e-5, rtol=0)
    back = scatter_scored(torch.arange(1.0, len(index) + 1), index, (ids.shape[0], ids.shape[1] - c))
    assert bool((back[cm[:, c:] == 0] == 0).all()) and back[cm[:, c:].bool()].tolist() == list(range(1, len(index) + 1))


def test_unsupported_models_fall_back():
    model = _llama()
    assert lean_support(model, 13, mode="train")[0]

    class Wrapper(nn.Module):  # DDP-like: the HF model in .module, its own forward
        def __init__(self, m):
            super().__init__()
            self.module = m

        def forward(self, **kw):
            return self.module(**kw)

    ok, why = lean_support(Wrapper(model), mode="train")
    assert not ok and "ForCausalLM" in why

    from peft import LoraConfig, get_peft_model

    peft_model = get_peft_model(_llama(), LoraConfig(r=2, target_modules=["q_proj", "v_proj"], lora_dropout=0.1))
    ok, why = lean_support(peft_model, mode="train")
    assert not ok and "dropout" in why  # the lean path draws no dropout masks
    assert not lean_support(peft_model.get_base_model(), mode="train")[0]  # LoRA layers inside

    gc = _llama()
    gc.gradient_checkpointing_enable()
    ok, why = lean_support(gc, mode="train")
    assert not ok and "checkpointing" in why

    ok, why = lean_support(_llama(attention_dropout=0.1), mode="train")
    assert not ok and "dropout" in why

    ok, why = lean_support(_llama(hidden_act="gelu"), mode="train")
    assert not ok and "hidden_act" in why

    ok, why = lean_support(_llama().double(), mode="train")
    assert not ok and "fp32" in why

    hooked = _llama()
    hooked.model.layers[0].mlp.register_forward_hook(lambda *a: None)
    assert not lean_support(hooked, mode="train")[0]

    from transformers import MistralConfig, MistralForCausalLM

    windowed = MistralForCausalLM(MistralConfig(vocab_size=V, hidden_size=64, intermediate_size=96,
                                                num_hidden_layers=1, num_attention_heads=4, num_key_value_heads=2,
                                                sliding_window=8))
    assert lean_support(windowed, 8, mode="train")[0] and not lean_support(windowed, 9, mode="train")[0]

    # The wrapped / adapted / checkpointed models still give HF's numbers through sequence_logprobs.
    ids, am, cm = _batch("left")
    ref, _ = sequence_logprobs(model, ids, am, cm)
    out, _ = sequence_logprobs(Wrapper(model), ids, am, cm)
    torch.testing.assert_close(out, ref)

    before = support.ENABLED
    try:
        support.ENABLED = False
        ok, why = lean_support(model, mode="train")
        assert not ok and "disabled" in why
    finally:
        support.ENABLED = before


def test_environment_variable_turns_it_off(monkeypatch):
    try:
        monkeypatch.setenv("POSTTRAIN_LEAN_TRAIN", "0")
        assert importlib.reload(support).ENABLED is False
        monkeypatch.setenv("POSTTRAIN_LEAN_TRAIN", "1")
        assert importlib.reload(support).ENABLED is True
    finally:
        monkeypatch.delenv("POSTTRAIN_LEAN_TRAIN")
        importlib.reload(support)


def test_fused_token_logprobs_equal_autograd():
    from posttrain.logprobs import token_logprobs

    g = torch.Generator().manual_seed(0)
    logits = (4 * torch.randn(3, 5, 11, generator=g)).requires_grad_()
    targets = torch.randint(0, 11, (3, 5), generator=g)
    w = torch.randn(3, 5, generator=g)
    lp0, e0 = token_logprobs(logits, targets, return_entropy=True, entropy_grad=False)
    (g0,) = torch.autograd.grad((lp0 * w).sum(), logits)
    lp1, e1 = lean_train.token_logprobs_fused(logits, targets, return_entropy=True)
    (g1,) = torch.autograd.grad((lp1 * w).sum(), logits)
    torch.testing.assert_close(lp1, lp0)
    torch.testing.assert_close(e1, e0)
    torch.testing.assert_close(g1, g0)
    assert not e1.requires_grad
    # with the entropy's gradient
    lp0, e0 = token_logprobs(logits, targets, return_entropy=True)
    (g0,) = torch.autograd.grad((lp0 * w).sum() + (e0 * w.flip(0)).sum(), logits)
    lp1, e1 = lean_train.token_logprobs_fused(logits, targets, return_entropy=True, entropy_grad=True)
    (g1,) = torch.autograd.grad((lp1 * w).sum() + (e1 * w.flip(0)).sum(), logits)
    torch.testing.assert_close(e1, e0)
    torch.testing.assert_close(g1, g0)


def _grouped_batch(groups=3, k=4, P=6, S=8, seed=0):
    """GRPO-like rows: `groups` prompts (left-padded to P columns, lengths differ) x `k` completions each
    (right-padded to S columns, lengths differ), rows of a group consecutive except the last group, which is
    interleaved with the others to check that grouping does not rely on order."""
    g = torch.Generator().manual_seed(seed)
    B, T = groups * k, P + S
    ids = torch.randint(3, V, (B, T), generator=g)
    am = torch.zeros(B, T, dtype=torch.long)
    order = list(range(B))
    order[-1], order[1] = order[1], order[-1]
    for j, r in enumerate(order):
        grp, i = divmod(j, k)
        plen = P - grp  # prompt lengths P, P-1, ...
        am[r, P - plen:P + max(S - i, 0)] = 1  # completion i of a group: S - i tokens (at least 0)
        ids[r, :P] = torch.randint(3, V, (P,), generator=torch.Generator().manual_seed(100 + grp))
    ids = ids * am
    cm = am.clone()
    cm[:, :P] = 0
    return ids, am, cm


@pytest.mark.parametrize("name", ["llama-mha-tied", "qwen2-gqa-bias", "llama-biases"])
def test_shared_prefix_forward_equals_unshared(name):
    """lean_forward_shared (each distinct prompt run once) gives the unshared lean forward's logits and every
    parameter's gradient; sequence_logprobs takes it for GRPO-like batches and agrees with the HF forward."""
    model = MODELS[name]()
    ids, am, cm = _grouped_batch()
    B, T = ids.shape
    c = 6
    first, row_of = lean_train.shared_prefix_rows(ids, am, c)
    assert len(first) == 3 and sorted(row_of.tolist()) == [0] * 4 + [1] * 4 + [2] * 4
    assert all(bool((ids[r, :c] == ids[first[row_of[r]], :c]).all()) for r in range(B))
    w = torch.randn(B, T - c, V, generator=torch.Generator().manual_seed(3))

    def run(shared):
        model.zero_grad(set_to_none=True)
        if shared:
            out = lean_train.lean_forward_shared(model, ids, am, c, first, row_of, temperature=0.8)
        else:
            out = lean_train.lean_forward(model, ids, am, position_ids_from_mask(am), positions=slice(c - 1, T - 1),
                                          temperature=0.8)
        # only real positions matter (pad rows' outputs are never used): weight them out
        keep = am[:, c - 1:T - 1].bool() & am[:, c:].bool()
        (out * w * keep[..., None]).sum().backward()
        return out.detach() * keep[..., None], {n: p.grad.clone() for n, p in model.named_parameters()}

    out0, g0 = run(False)
    out1, g1 = run(True)
    torch.testing.assert_close(out1, out0, atol=1e-5, rtol=1e-5)
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)

    calls = []
    real = lean_train.lean_hidden_shared
    try:
        lean_train.lean_hidden_shared = lambda *a, **k: calls.append(1) or real(*a, **k)
        lp1, _ = sequence_logprobs(model, ids, am, cm)
    finally:
        lean_train.lean_hidden_shared = real
    assert calls, "sequence_logprobs did not share the prompts"
    before = support.ENABLED
    support.ENABLED = False
    try:
        lp0, _ = sequence_logprobs(model, ids, am, cm)
    finally:
        support.ENABLED = before
    torch.testing.assert_close(lp1, lp0, atol=1e-5, rtol=2e-6)


@pytest.mark.parametrize("groups,k,S", [(1, 4, 1), (1, 3, 3), (2, 2, 2)])
def test_shared_prefix_edge_shapes(groups, k, S):
    """One prompt for every row, one-column completions, rows without any completion token: still equal."""
    model = MODELS["llama-gqa-untied"]()
    ids, am, _ = _grouped_batch(groups=groups, k=k, P=5, S=S)
    B, T = ids.shape
    first, row_of = lean_train.shared_prefix_rows(ids, am, 5)
    assert len(first) == groups
    with torch.no_grad():
        out1 = lean_train.lean_forward_shared(model, ids, am, 5, first, row_of)
        out0 = lean_train.lean_forward(model, ids, am, position_ids_from_mask(am), positions=slice(4, T - 1))
    keep = am[:, 4:T - 1].bool()  # logits at real positions (the last prompt column is always real)
    torch.testing.assert_close(out1[keep], out0[keep], atol=1e-5, rtol=1e-5)


def test_distinct_prompts_do_not_share():
    ids, am, cm = _batch("both")
    first, row_of = lean_train.shared_prefix_rows(ids, am, 5)
    assert len(first) == ids.shape[0] and first[row_of].tolist() == list(range(ids.shape[0]))


def _seqcls(kind="llama"):
    """A one-label sequence-classification model (reward / value model) with perturbed norms and biases."""
    return _build(kind, "ForSequenceClassification")


@pytest.mark.parametrize("kind", ["llama", "qwen2"])
def test_reward_and_value_forwards_equal_hf(kind):
    """scoring.reward_forward and ppo.token_values take lean_hidden for a plain sequence-classification model:
    same rewards / values and gradients as the model's own forward."""
    from posttrain.scoring import reward_forward
    from posttrain.trainers.ppo import token_values

    model = _seqcls(kind)
    assert lean_support(model, 13, head="score", mode="train")[0]
    assert not lean_support(model, 13, mode="train")[0]  # not a causal LM
    ids, am, _ = _batch("left")
    w = torch.randn(ids.shape, generator=torch.Generator().manual_seed(5))
    real = am.clone()  # values[:, t] come from token t-1: compare where both are real (pad rows are never used)
    real[:, 1:] *= am[:, :-1]
    real[:, 0] = 0

    def run(enabled, fn):
        before = support.ENABLED
        support.ENABLED = enabled
        try:
            model.zero_grad(set_to_none=True)
            out = fn(model, ids, am)
            (out * (w[:, 0] if out.dim() == 1 else w * real)).sum().backward()
            return out.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}
        finally:
            support.ENABLED = before

    for fn in (reward_forward, token_values):
        out0, g0 = run(False, fn)
        out1, g1 = run(True, fn)
        if out0.dim() == 2:
            out0, out1 = out0 * real, out1 * real
        torch.testing.assert_close(out1, out0, atol=1e-5, rtol=1e-5)
        for n in g0:
            torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)


@pytest.mark.parametrize("kind", ["llama", "qwen2"])
def test_pair_rewards_share_the_prompt_on_the_lean_path_with_the_same_numbers(kind, monkeypatch):
    """scoring.pair_rewards packs each pair into one row (prompt once, rejected never seeing chosen) on the lean
    path: the same (2B,) rewards and gradients as two left-padded rows through the model's own forward, for pairs
    of different prompt, chosen and rejected lengths; and it does run fewer tokens (the prompt once)."""
    from posttrain.data import TokenizedPair
    from posttrain.scoring import pair_rewards

    model = _seqcls(kind)
    g = torch.Generator().manual_seed(2)

    def toks(n):
        return torch.randint(3, V, (n,), generator=g).tolist()

    pairs = [TokenizedPair(prompt=toks(p), chosen=toks(c), rejected=toks(r), row=i)
             for i, (p, c, r) in enumerate([(5, 3, 6), (2, 7, 1), (9, 4, 4)])]
    w = torch.randn(6, generator=g)
    seen = []
    real_forward = lean_train._rows_forward
    monkeypatch.setattr(lean_train, "_rows_forward", lambda m, ids, *a, **k: seen.append(ids.numel()) or
                        real_forward(m, ids, *a, **k))

    def run(enabled):
        monkeypatch.setattr(support, "ENABLED", enabled)
        model.zero_grad(set_to_none=True)
        r = pair_rewards(model, pairs, 0)
        (r * w).sum().backward()
        return r.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}

    (r0, g0), (r1, g1) = run(False), run(True)
    assert seen == [3 * 17]  # one packed row per pair, as wide as the longest prompt + chosen + rejected (9 + 4 + 4)
    torch.testing.assert_close(r1, r0, atol=1e-5, rtol=1e-5)
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)


def test_sharded_parameters_are_not_read_by_the_lean_paths():
    """FSDP-wrapped modules or DeepSpeed ZeRO-3 partitioned parameters hold only a shard outside the model's own
    forward: both lean paths (training forward, rollout engine) refuse them and say why."""

    model = _llama()
    assert lean_support(model, 13, mode="train")[0] and lean_support(model, 13, mode="decode")[0]
    model.model.layers[0].mlp.up_proj.weight.ds_id = 7  # what ZeRO-3 puts on its parameters
    for ok, why in (lean_support(model, 13, mode="train"), lean_support(model, 13, mode="decode")):
        assert not ok and "ZeRO-3" in why
    del model.model.layers[0].mlp.up_proj.weight.ds_id

    class FullyShardedDataParallel(nn.Module):  # stands in for torch's FSDP wrapper of one decoder layer
        def __init__(self, inner):
            super().__init__()
            self._fsdp_wrapped_module = inner

    model.model.add_module("wrapped", FullyShardedDataParallel(nn.Linear(2, 2)))
    for ok, why in (lean_support(model, 13, mode="train"), lean_support(model, 13, mode="decode")):
        assert not ok and "FSDP" in why


@pytest.mark.parametrize("name", ["llama-mha-tied", "qwen2-gqa-bias"])
def test_packed_logprobs_lean_equals_hf(name):
    """DPO's shared-prompt rows (prompt, chosen, rejected; a 4D mask): the lean packed forward gives the HF
    forward's log-probs and gradients."""
    from posttrain.logprobs import packed_logprobs
    from posttrain.data import TokenizedPair, collate_shared_prompt

    model = MODELS[name]()
    g = torch.Generator().manual_seed(4)

    def toks(n):
        return torch.randint(3, V, (n,), generator=g).tolist()

    pairs = [TokenizedPair(toks(p), toks(c), toks(r), i + 1) for i, (p, c, r) in enumerate([(4, 3, 5), (6, 2, 2), (3, 5, 4)])]
    b = collate_shared_prompt(pairs, 0)
    w = torch.randn(b["targets"].shape, generator=g)

    def run(enabled):
        before = support.ENABLED
        support.ENABLED = enabled
        try:
            model.zero_grad(set_to_none=True)
            lp = packed_logprobs(model, b["input_ids"], b["position_ids"], b["allowed"], b["pred_index"],
                                 b["targets"], b["target_mask"])
            (lp * w).sum().backward()
            return lp.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}
        finally:
            support.ENABLED = before

    lp0, g0 = run(False)
    calls = []
    real = lean_train.lean_packed_hidden
    lean_train.lean_packed_hidden = lambda *a, **k: calls.append(1) or real(*a, **k)
    try:
        lp1, g1 = run(True)
    finally:
        lean_train.lean_packed_hidden = real
    assert calls, "the lean packed path was not taken"
    torch.testing.assert_close(lp1, lp0, atol=1e-5, rtol=2e-6)
    assert bool((lp1[b["target_mask"] == 0] == 0).all())
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)


def _logprobs_and_grads(model, ids, am, cm, lean: bool, monkeypatch):
    """sequence_logprobs under autograd, lean path on or off: (log-probs, {parameter: gradient})."""
    monkeypatch.setattr(support, "ENABLED", lean)
    model.zero_grad(set_to_none=True)
    lp, _ = sequence_logprobs(model, ids, am, cm)
    (lp * torch.linspace(-1, 1, lp.numel()).view_as(lp)).sum().backward()
    return lp.detach(), {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}


def _cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.nn.functional.cosine_similarity(a.flatten(), b.flatten(), 0))


@pytest.mark.parametrize("name", ["llama-mha-tied", "qwen2-gqa-bias", "llama-biases"])
def test_lean_forward_runs_under_bf16_autocast_as_the_hf_forward_does(name, monkeypatch):
    """Under torch.autocast(bf16) the lean training forward runs its matmuls in bf16 (not the fp32 numbers) and
    lands as close to the fp32 log-probs and gradients as the HF forward under the same autocast does; log-probs
    and gradients stay fp32. The engine's decoder still steps aside (generation precision is rollout.dtype's)."""
    from posttrain.rollout import generate

    model = MODELS[name]()
    ids, am, cm = _batch("both")
    lp32, g32 = _logprobs_and_grads(model, ids, am, cm, True, monkeypatch)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        ok, why = lean_support(model, 13, mode="train")
        assert ok and "bf16 autocast" in why, why
        ok, why = lean_support(model, 13, mode="decode")
        assert not ok and "autocast" in why
        lp_lean, g_lean = _logprobs_and_grads(model, ids, am, cm, True, monkeypatch)
        lp_hf, g_hf = _logprobs_and_grads(model, ids, am, cm, False, monkeypatch)
        out = generate(model, None, [[5, 6, 7]], max_new_tokens=3, greedy=True)
    assert len(out[0].completion_ids) == 3
    assert lp_lean.dtype == torch.float32 and all(g.dtype == torch.float32 for g in g_lean.values())
    err_lean, err_hf = float((lp_lean - lp32).abs().max()), float((lp_hf - lp32).abs().max())
    print(f"max |bf16 - fp32| log-prob: lean {err_lean:.4f}, HF {err_hf:.4f}; grad cosines lean",
          {n: round(_cosine(g_lean[n], g32[n]), 4) for n in list(g32)[:3]})
    assert 0 < err_lean < 0.5 and 0 < err_hf < 0.5  # bf16 compute happened on both paths: close, not equal
    # bf16 rounds at ~2^-8 relative: the two bf16 paths differ from fp32 by the same order (measured 0.3-3x of
    # each other over these models); 4x and an absolute floor leave room for other CPUs' kernels
    assert err_lean <= 4 * err_hf + 0.02, (err_lean, err_hf)
    assert g_lean.keys() == g32.keys() == g_hf.keys()
    for n in g32:
        if float(g32[n].abs().max()) > 0:
            assert _cosine(g_lean[n], g32[n]) > 0.98, n
    assert bool((lp_lean[cm == 0] == 0).all())
    monkeypatch.setattr(support, "ENABLED", True)
    assert lean_support(model, 13, mode="train")[0] and "bf16" not in lean_support(model, 13, mode="train")[1]


def test_fp16_autocast_and_accelerates_other_precisions_fall_back(monkeypatch):
    """fp16 autocast (it needs loss scaling) falls back to the HF forward. accelerate's mixed precision
    (Accelerator.prepare_model with native amp keeps the original forward in `_original_forward` and wraps
    `forward` in autocast) never reaches the lean path through `forward`, so the lean path enters the same bf16
    autocast itself: the log-probs equal those under an explicit torch.autocast; with fp16 the patched forward
    is used. Done by hand, as accelerate does, with the process's accelerate precision patched, because a real
    Accelerator would fix the process-wide AcceleratorState."""
    import types

    model = _llama()
    ids, am, cm = _batch("both")
    with torch.autocast("cpu", dtype=torch.float16):
        ok, why = lean_support(model, 13, mode="train")
    assert not ok and "bf16 autocast only" in why
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        lp_autocast, _ = sequence_logprobs(model, ids, am, cm)
    with torch.no_grad():
        lp32, _ = sequence_logprobs(model, ids, am, cm)

    prepared = model
    prepared._original_forward = prepared.forward
    inner_forward = type(prepared).forward

    def autocast_forward(self, *a, **k):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return inner_forward(self, *a, **k)

    prepared.forward = types.MethodType(autocast_forward, prepared)
    monkeypatch.setattr(support, "_accelerate_mixed_precision", lambda: "bf16")
    ok, why = lean_support(prepared, 13, mode="train")
    assert ok and "bf16 autocast" in why, why
    calls = []
    real = lean_train.lean_hidden_shared, lean_train.lean_last_layer
    monkeypatch.setattr(lean_train, "lean_last_layer", lambda *a, **k: calls.append(1) or real[1](*a, **k))
    with torch.no_grad():
        lp_mp, _ = sequence_logprobs(prepared, ids, am, cm)
    assert calls, "the lean path was not taken"
    torch.testing.assert_close(lp_mp, lp_autocast, atol=0, rtol=0)
    assert float((lp_mp - lp32).abs().max()) > 0  # bf16, not the fp32 numbers
    monkeypatch.setattr(support, "_accelerate_mixed_precision", lambda: "fp16")
    ok, why = lean_support(prepared, 13, mode="train")
    assert not ok and "mixed precision 'fp16'" in why
    with torch.no_grad():
        lp_fp16, _ = sequence_logprobs(prepared, ids, am, cm)  # the patched (bf16 here) forward
    assert lp_fp16.dtype == torch.float32 and 0 < float((lp_fp16 - lp32).abs().max()) < 0.5


# ----------------------------------------------------------------------------- the chunked head (real vocabularies)
@pytest.mark.parametrize("name", ["llama-mha-tied", "qwen2-gqa-bias", "llama-biases"])
@pytest.mark.parametrize("temperature,entropy_grad", [(1.0, False), (0.7, True)])
def test_chunked_head_gives_the_fused_heads_numbers_and_gradients(name, temperature, entropy_grad):
    """lean_token_logprobs in row chunks (never all logits at once) = the one-pass fused head: log-probs,
    entropies and every parameter's gradient (tied embeddings, a head bias, a temperature, entropy_grad)."""
    model = MODELS[name]()
    g = torch.Generator().manual_seed(5)
    x = torch.randn(3, 7, model.config.hidden_size, generator=g, requires_grad=True)
    targets = torch.randint(0, V, (3, 7), generator=g)
    wl, we = torch.randn(3, 7, generator=g), torch.randn(3, 7, generator=g)

    def run(chunk_elements):
        model.zero_grad(set_to_none=True)
        x.grad = None
        lp, ent = lean_train.lean_token_logprobs(model, x, targets, temperature, True, entropy_grad,
                                                 chunk_elements=chunk_elements)
        ((lp * wl).sum() + ((ent * we).sum() if entropy_grad else 0)).backward()
        grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
        return lp.detach(), ent.detach(), x.grad.clone(), grads

    lp0, ent0, gx0, g0 = run(1 << 30)  # one fused pass
    lp1, ent1, gx1, g1 = run(4 * V)  # 4 rows per chunk: 6 chunks, the last one short
    torch.testing.assert_close(lp1, lp0, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(ent1, ent0, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(gx1, gx0, atol=1e-5, rtol=1e-4)
    assert g1.keys() == g0.keys()
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)


def test_chunked_head_under_bf16_autocast_matches_the_fused_head():
    """Under bf16 autocast both heads run the head matmul in bf16 and the softmax in fp32: the chunked head's
    explicit casts (forward and the recomputing backward) give the fused head's numbers and gradients."""
    model = MODELS["llama-biases"]()
    g = torch.Generator().manual_seed(5)
    x = torch.randn(3, 7, model.config.hidden_size, generator=g, requires_grad=True)
    targets = torch.randint(0, V, (3, 7), generator=g)
    w = torch.randn(3, 7, generator=g)

    def run(chunk_elements, autocast=True):
        model.zero_grad(set_to_none=True)
        x.grad = None
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            lp, _ = lean_train.lean_token_logprobs(model, x, targets, chunk_elements=chunk_elements)
        (lp * w).sum().backward()
        return lp.detach(), x.grad.clone(), model.lm_head.weight.grad.clone()

    lp0, gx0, gw0 = run(1 << 30)
    lp1, gx1, gw1 = run(4 * V)
    lp32, gx32, gw32 = run(1 << 30, autocast=False)
    assert lp1.dtype == torch.float32 and float((lp1 - lp32).abs().max()) > 0  # bf16 matmuls, not fp32's
    torch.testing.assert_close(lp1, lp0, atol=2e-2, rtol=0)  # the same bf16 rounding of the logits
    assert _cosine(gx1, gx0) > 0.999 and _cosine(gw1, gw0) > 0.999
    assert _cosine(gx1, gx32) > 0.98 and _cosine(gw1, gw32) > 0.98


def test_the_chunked_head_never_keeps_logits_for_the_backward(monkeypatch):
    """What autograd saves for the backward of a chunked call holds no (N, V) tensor (the fused path saves the
    (N, V) softmax), and sequence_logprobs takes the chunked path when the logits pass the threshold."""
    big = 4096  # a vocabulary much wider than the model, as real ones are (49k vs d=576)
    model = _llama(vocab_size=big, hidden_size=32, intermediate_size=48, tie_word_embeddings=False)
    ids = torch.randint(3, big, (4, 12), generator=torch.Generator().manual_seed(1))
    am = torch.ones_like(ids)
    N = 4 * 11

    def saved_sizes(chunk_elements):
        monkeypatch.setattr(lean_train, "HEAD_CHUNK_ELEMENTS", chunk_elements)
        sizes = []
        with torch.autograd.graph.saved_tensors_hooks(lambda t: sizes.append(t.numel()) or t, lambda t: t):
            lp, _ = sequence_logprobs(model, ids, am)
        return lp, sizes

    lp_fused, fused = saved_sizes(1 << 30)
    lp_chunked, chunked = saved_sizes(2 * big)
    assert max(fused) >= N * big  # the fused head keeps the softmax
    assert max(chunked) <= big * 32, (max(chunked), N * big)  # the head weight is the largest thing kept
    torch.testing.assert_close(lp_chunked, lp_fused, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("tokens", [8, 400])  # fewer / more tokens than the projections' rows (192 here)
def test_the_norm_weight_on_the_activations_or_folded_into_the_weights_gives_the_same_numbers(tokens):
    """`_normed` multiplies the RMSNorm weight into the activations (few tokens) or into each following weight
    (many tokens); either way the projections' outputs and every gradient equal HF's (x_normed * g) @ W.T."""
    g = torch.Generator().manual_seed(0)
    norm = nn.Module()
    norm.weight = nn.Parameter(1 + 0.3 * torch.randn(16, generator=g))
    norm.variance_epsilon = 1e-6
    lins = [nn.Linear(16, rows, bias=False) for rows in (96, 96)]
    ws = [m.weight for m in lins]
    x = torch.randn(tokens, 16, generator=g, requires_grad=True)
    up = torch.randn(tokens, 96, generator=g)

    def run(lean: bool):
        for p in (norm.weight, x, *ws):
            p.grad = None
        if lean:
            h, fold = lean_train._normed(x, norm, tuple(lins))
            assert (fold is None) == (tokens <= 192)  # folded only past the rows
            outs = [lean_train._proj(m, h, fold) for m in lins]
        else:
            h = lean_train._rms(x, 1e-6) * norm.weight
            outs = [torch.nn.functional.linear(h, w) for w in ws]
        out = sum((o * up).sum() for o in outs)
        out.backward()
        return out.detach(), [p.grad.clone() for p in (norm.weight, x, *ws)]

    (o1, g1), (o0, g0) = run(True), run(False)
    torch.testing.assert_close(o1, o0, rtol=1e-5, atol=1e-3)
    for a, b in zip(g1, g0):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4 * float(b.abs().max()))


@pytest.mark.parametrize("shape", ["causal", "padded", "suffix"])
def test_explicit_bf16_attention_matches_the_fused_kernel(shape, monkeypatch):
    """Under bf16 autocast on a CPU `_sdpa` runs short attentions as explicit matmuls with an fp32 softmax; it
    attends where F.scaled_dot_product_attention does (causal, a padding mask whose pad queries see themselves,
    fewer queries than keys as in the shared-prefix forward, GQA), within bf16 rounding, gradients included."""
    model = MODELS["llama-gqa-untied"]()  # 4 query heads over 2 kv heads, D = 16
    H, Hkv, D, _ = lean_train._dims(model)
    g = torch.Generator().manual_seed(3)
    B, Tq, Tk = 3, (5 if shape == "suffix" else 9), 9
    q = torch.randn(B, H, Tq, D, generator=g, requires_grad=True)
    k = torch.randn(B, Hkv, Tk, D, generator=g, requires_grad=True)
    v = torch.randn(B, Hkv, Tk, D, generator=g, requires_grad=True)
    allowed = None
    if shape != "causal":
        valid = torch.ones(B, Tk, dtype=torch.bool)
        valid[1, :3] = False  # row 1 left-padded
        allowed = torch.ones(Tq, Tk, dtype=torch.bool).tril_(Tk - Tq)[None, None] & valid[:, None, None, :]
        own = torch.ones(Tq, Tk, dtype=torch.bool).tril_(Tk - Tq) & torch.ones(Tq, Tk, dtype=torch.bool).triu_(Tk - Tq)
        allowed = allowed | own[None, None]  # pad queries see themselves
    w = torch.randn(B, H, Tq, D, generator=g)

    def run(max_keys):
        monkeypatch.setattr(lean_train, "EXPLICIT_ATTENTION_MAX_KEYS", max_keys)
        for t in (q, k, v):
            t.grad = None
        with torch.autocast("cpu", dtype=torch.bfloat16):
            o = lean_train._sdpa(model, q, k, v, allowed)
        (o.float() * w).sum().backward()
        return o.float().detach(), [t.grad.clone() for t in (q, k, v)]

    (o1, g1), (o0, g0) = run(1 << 20), run(0)  # explicit, the kernel
    torch.testing.assert_close(o1, o0, atol=3e-2, rtol=0)  # both bf16: ~2^-8 relative of values ~1
    for a, b in zip(g1, g0):
        assert _cosine(a, b) > 0.999


def _lora_model(**kw):
    """A perturbed llama under peft LoRA adapters on every projection, B made non-zero so the deltas count."""
    from peft import LoraConfig, get_peft_model

    model = get_peft_model(_llama(**kw), LoraConfig(r=4, lora_alpha=8, target_modules=[
        "q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj"]))
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():
        for n, p in model.named_parameters():
            if "lora_B" in n:
                p.copy_(0.05 * torch.randn(p.shape, generator=g))
    return model


@pytest.mark.parametrize("padding", ["none", "both"])
def test_lora_models_run_the_lean_forward_with_hf_numbers(padding, monkeypatch):
    """A peft LoRA model (no dropout) takes the lean training forward: the same log-probs as peft's own forward and
    the same gradients of every adapter (the base stays frozen, and gets none), adapters disabled too (a reference
    under `disable_adapter`); biases on the projections and GQA included."""
    model = _lora_model(num_key_value_heads=2, attention_bias=True)
    ok, why = lean_support(model, 13, mode="train")
    assert ok and "LoRA" in why, why
    ids, am, cm = _batch(padding)

    def run(lean: bool):
        lp, grads = _logprobs_and_grads(model, ids, am, cm, lean, monkeypatch)
        with torch.no_grad(), model.disable_adapter():
            off, _ = sequence_logprobs(model, ids, am, cm)
        return lp, grads, off

    (lp0, g0, off0), (lp1, g1, off1) = run(False), run(True)
    torch.testing.assert_close(lp1, lp0, atol=1e-5, rtol=2e-6)
    torch.testing.assert_close(off1, off0, atol=1e-5, rtol=2e-6)
    assert float((off0 - lp0).abs().max()) > 1e-3  # the adapters do change the numbers
    assert g1.keys() == g0.keys() and g0 and all("lora_" in n for n in g0)
    for n in g0:
        torch.testing.assert_close(g1[n], g0[n], rtol=1e-4, atol=1e-5 * float(g0[n].abs().max()), msg=n)


def test_lora_under_bf16_autocast_casts_the_frozen_base_once(monkeypatch):
    """Under bf16 autocast a LoRA model's frozen base weights are cast to bf16 once and reused (`_frozen_cast`),
    a fresh copy after an in-place change of the weight; the log-probs stay as close to fp32 as the HF forward's
    under the same autocast, and the adapters' gradients point the same way."""
    model = _lora_model()
    ids, am, cm = _batch("both")
    lp32, g32 = _logprobs_and_grads(model, ids, am, cm, True, monkeypatch)
    lean_train._FROZEN_CASTS.clear()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        lp_lean, g_lean = _logprobs_and_grads(model, ids, am, cm, True, monkeypatch)
        copies = {id(t) for _, e in lean_train._FROZEN_CASTS.values() for _, t in e.values()}
        assert len(copies) == 7 * 2  # every projection of both layers, cast once
        again, _ = _logprobs_and_grads(model, ids, am, cm, True, monkeypatch)
        assert {id(t) for _, e in lean_train._FROZEN_CASTS.values() for _, t in e.values()} == copies  # reused
        torch.testing.assert_close(again, lp_lean, atol=0, rtol=0)
        lp_hf, _ = _logprobs_and_grads(model, ids, am, cm, False, monkeypatch)
        w = model.get_base_model().model.layers[0].mlp.down_proj.base_layer.weight
        with torch.no_grad():
            w.mul_(1.5)  # e.g. a checkpoint loaded in place
        changed, _ = _logprobs_and_grads(model, ids, am, cm, True, monkeypatch)
    assert float((changed - lp_lean).abs().max()) > 0  # the new weight was cast, not the stale copy
    err_lean, err_hf = float((lp_lean - lp32).abs().max()), float((lp_hf - lp32).abs().max())
    assert 0 < err_lean < 0.5 and err_lean <= 4 * err_hf + 0.02, (err_lean, err_hf)
    for n in g32:
        assert _cosine(g_lean[n], g32[n]) > 0.98, n


@pytest.mark.parametrize("with_weight", [True, False])
def test_the_rms_norms_written_out_backward_is_the_derivative(with_weight):
    """`_RMSNorm`'s hand-written backward against numerical derivatives (float64 gradcheck), and its forward equal
    to HF's LlamaRMSNorm formula; under bf16 autocast its output is bf16 (the projections' input, cast once) and
    its gradients stay in the input's dtype."""
    torch.manual_seed(0)
    x = torch.randn(5, 8, dtype=torch.float64, requires_grad=True)
    g = (torch.rand(8, dtype=torch.float64) + 0.5).requires_grad_() if with_weight else None
    fn = lambda x, g: lean_train._RMSNorm.apply(x, g, 1e-6, None)
    assert torch.autograd.gradcheck(fn, (x, g))
    hf = x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + 1e-6) * (g if with_weight else 1.0)
    torch.testing.assert_close(fn(x, g), hf, rtol=0, atol=1e-15)
    x32 = x.detach().float().requires_grad_()
    g32 = g.detach().float().requires_grad_() if with_weight else None
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = lean_train._RMSNorm.apply(x32, g32, 1e-6, lean_train._autocast_dtype(x32.device))
    assert y.dtype == torch.bfloat16
    (y.float() * torch.arange(8.0)).sum().backward()
    assert x32.grad.dtype == torch.float32 and (not with_weight or g32.grad.dtype == torch.float32)
