"""Frozen references take their log-probs in the run's precision: under run.mixed_precision=bf16 the same bf16
autocast as the policy's (accelerate only patches the forward of the models it prepared, and a reference is never
prepared), as TRL's reference and our distillation teacher do."""
import torch
from transformers import LlamaConfig, LlamaForCausalLM

from posttrain import loop, sharding
from posttrain.logprobs import batched_logprobs
from posttrain.data import TokenizedPair


def _frozen_model():
    torch.manual_seed(0)
    cfg = LlamaConfig(vocab_size=64, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                      num_attention_heads=4, max_position_embeddings=64)
    return LlamaForCausalLM(cfg).eval().requires_grad_(False)


def _batch():
    g = torch.Generator().manual_seed(1)
    ids = torch.randint(3, 64, (3, 12), generator=g)
    cm = torch.zeros_like(ids)
    cm[:, 5:] = 1
    return {"input_ids": ids, "attention_mask": torch.ones_like(ids), "completion_mask": cm}


def test_sharded_logprobs_run_a_frozen_reference_in_the_runs_precision():
    model, batch = _frozen_model(), _batch()
    fp32 = batched_logprobs(model, batch, 4)[0]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        bf16 = batched_logprobs(model, batch, 4)[0]
    assert float((bf16 - fp32).abs().max()) > 1e-4  # the two precisions give different numbers here
    got = sharding.sharded_logprobs(loop.setup(0, mixed_precision="bf16"), model, batch, 4)
    torch.testing.assert_close(got, bf16, rtol=0, atol=0)
    assert not torch.is_autocast_enabled("cpu")  # the context ends with the call
    torch.testing.assert_close(sharding.sharded_logprobs(loop.setup(0), model, batch, 4), fp32, rtol=0, atol=0)
    torch.testing.assert_close(sharding.sharded_logprobs(None, model, batch, 4), fp32, rtol=0, atol=0)


def test_dpos_reference_log_probs_are_taken_under_the_runs_autocast(monkeypatch):
    """The precomputed reference (training and held-out pairs), and a live reference inside the loss."""
    from posttrain.trainers import dpo

    seen = []

    def reference_logps(model, pairs, *a, **k):
        seen.append(torch.is_autocast_enabled("cpu"))
        return {k: torch.zeros(len(pairs)) for k in ("chosen", "rejected", "chosen_tokens", "rejected_tokens")}

    monkeypatch.setattr(dpo, "reference_logps", reference_logps)
    pairs = [TokenizedPair([1, 2], [3, 4], [5, 6], i + 1) for i in range(4)]
    data = dpo.PairData(train=pairs, heldout=pairs[:2], source="test", gold_rows=[], online_rows=[])
    cfg = dpo.DPOConfig(batch_size=2, max_steps=2)
    bf16 = lambda: torch.autocast("cpu", dtype=torch.bfloat16)
    dpo.precompute_reference(cfg, None, data, 0, 0, lambda *a: None, bf16)
    assert seen == [True, True, True]  # each step's new training pairs (2 steps), then the held-out ones

    def pair_logps(model, batch):
        seen.append((model, torch.is_autocast_enabled("cpu")))
        return torch.zeros(4, requires_grad=model == "policy"), torch.ones(4)  # 2 pairs: chosen, then rejected

    monkeypatch.setattr(dpo, "pair_logps", pair_logps)
    pool = dpo.Pool(pairs, None)
    dpo.micro_batch_loss(cfg, "policy", "reference", pool, [0, 1], 0, 2, bf16)
    assert seen[3:] == [("policy", False), ("reference", True)]
