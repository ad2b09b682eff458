"""PPO-for-RLHF on a tiny model: config errors, one test per implementation-detail flag, it learns, resume, NaN."""
import json
import math
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import posttrain.trainers.ppo as ppo
from posttrain.cli import main
from posttrain.scoring import ScoreResult
from posttrain.tasks import summarize


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def world(tmp_path_factory, tiny_lm, tiny_rm):
    """A random tiny 'SFT' model (tokenizer trained on the task) and a 'reward model' made from it."""
    root = tmp_path_factory.mktemp("ppo")
    short = root / "short.jsonl"  # 5-word documents: cheap iterations for the learning test
    short.write_text("".join(json.dumps({"prompt": "Document: " + " ".join(r["prompt"].split()[1:6]) + "\nSummary:",
                                         "completion": " x"}) + "\n" for r in summarize.make_examples(64, 0, "train")))
    return {"root": root, "sft": tiny_lm("tiny-summarize", max_length=256), "rm": tiny_rm("tiny-summarize"), "short": short}


class VowelScorer:
    """A hand-made reward the random model can learn in a few iterations: the fraction of vowels in the text."""

    name = "vowels"

    def score(self, prompts, completions, references=None):
        r = [sum(c in "aeiou" for c in t.lower()) / max(1, len(t)) for t in completions]
        return ScoreResult(r, {self.name: r})


@pytest.fixture
def vowels(monkeypatch):
    monkeypatch.setattr(ppo, "reward_scorer", lambda *a, **k: VowelScorer())


def _args(world, out: Path, *extra: str) -> list[str]:
    sft = out / "tiny-summarize" / "sft" / "final"
    if not sft.exists():
        sft.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(world["sft"], sft)  # the stage finds its "SFT model" and never runs SFT
    return ["ppo", "--recipe", "tiny-summarize", f"run.output_dir={out}", "reward=gold", "value_init=policy",
            "rollout_batch_size=8", "minibatch_size=4", "ppo_epochs=2", "max_steps=2", "max_new_tokens=8",
            "reward_norm=none", "eval_every=0", "eval_rows=8", "final_eval_rows=0", "save_every=0", "lr=1e-3",
            "value_lr=1e-3", "schedule=constant", "task.n_train=64", "task.n_eval=16", "run.quiet=true",
            "run.threads=1", *extra]  # pinned: not the recipe's


def _metrics(out: Path) -> list[dict]:
    return [json.loads(l) for l in (out / "tiny-summarize" / "ppo" / "metrics.jsonl").read_text().splitlines()]


# ----------------------------------------------------------------------------- config errors
@pytest.mark.parametrize("bad, message", [
    ("minibatch_size=3", "ppo.minibatch_size=3 must divide rollout_batch_size=8"),
    ("temperature=0", "ppo.temperature must be > 0"),
    ("ppo_epochs=0", "ppo.ppo_epochs must be >= 1"),
    ("kl_target=0", "ppo.kl_target must be > 0"),
    ("value_clip=-1", "ppo.value_clip must be >= 0"),
    ("reward_model=/nowhere", "ppo.reward_model '/nowhere' is not a reward-model directory"),
    ("rollout_batch_size=128", "ppo.rollout_batch_size=128 is more than the 64 training prompts"),
    ("kl_estimator=k2", "'ppo.kl_estimator': 'k2' is not one of 'k1', 'k3'"),
    ("task.train_file=SHORT", "ppo.reward=gold needs the task's meta in every training row"),
    ("policy_loss=gspo", "'ppo.policy_loss': 'gspo' is not one of 'clip', 'gspo_token', 'cispo'"),
    ("rollout_correction_cap=0.5", "ppo.rollout_correction_cap must be > 1"),
])
def test_config_errors_are_one_line_and_touch_nothing(world, tmp_path, capsys, bad, message):
    extra = [bad, "kl_control=adaptive"] if bad.startswith("kl_target") else [bad.replace("SHORT", str(world["short"]))]
    assert main(_args(world, tmp_path, *extra)) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "tiny-summarize" / "ppo").exists()


# ----------------------------------------------------------------------------- details 1-3: score shaping
def test_reward_normalisation_penalty_and_clipping_by_hand():
    raw = torch.tensor([1.0, 3.0, 5.0, -7.0])
    ended = torch.tensor([True, True, False, True])
    cfg = ppo.PPOConfig(reward_norm="init", missing_eos_penalty=1.0, reward_clip=3.0)
    # init: (raw - 1) / 2 = [0, 1, 2, -4]; row 2 never ended: -1 -> 1; clip to [-3, 3]
    assert ppo.shape_scores(raw, ended, cfg, {"mean": 1.0, "std": 2.0}).tolist() == [0.0, 1.0, 1.0, -3.0]
    cfg.reward_clip = 0.0  # off
    assert ppo.shape_scores(raw, ended, cfg, {"mean": 1.0, "std": 2.0}).tolist() == [0.0, 1.0, 1.0, -4.0]
    cfg.missing_eos_penalty = 0.0  # off
    assert ppo.shape_scores(raw, ended, cfg, {"mean": 1.0, "std": 2.0}).tolist() == [0.0, 1.0, 2.0, -4.0]
    cfg.reward_norm = "none"
    assert ppo.shape_scores(raw, ended, cfg, None).tolist() == raw.tolist()
    cfg.reward_norm = "batch"  # mean 0.5; unbiased var = (0.25 + 6.25 + 20.25 + 56.25) / 3 = 27.666...
    std = math.sqrt(83.0 / 3.0)
    torch.testing.assert_close(ppo.shape_scores(raw, ended, cfg, None),
                               torch.tensor([0.5 / std, 2.5 / std, 4.5 / std, -7.5 / std]))


def test_reward_norm_init_is_measured_on_sft_samples_and_saved(world, tmp_path, vowels, capsys):
    out = tmp_path / "norm"
    assert main(_args(world, out, "reward_norm=init", "reward_norm_prompts=16", "max_steps=1", "save_every=1",
                      "reward_clip=0", "missing_eos_penalty=0")) == 0
    assert "reward normalisation from 16 SFT samples" in capsys.readouterr().out
    state = torch.load(out / "tiny-summarize" / "ppo" / "checkpoints" / "step-000001" / "state.pt",
                       weights_only=False)
    norm = state["extra"]["reward_norm"]
    assert norm["n"] == 16 and 0.0 < norm["mean"] < 1.0 and norm["std"] > 0
    m = [r for r in _metrics(out) if "rollout/score" in r][0]
    assert m["rollout/score"] == pytest.approx((m["rollout/score_raw"] - norm["mean"]) / norm["std"], rel=1e-4)


# ----------------------------------------------------------------------------- details 4, 6, 7, 8: rewards, GAE
def _one_row():
    cm = torch.tensor([[False, True, True, True]])
    logps = torch.tensor([[0.0, -1.0, -2.0, -0.5]])
    ref = torch.tensor([[0.0, -1.1, -1.8, -0.8]])  # log pi - log ref = [0.1, -0.2, 0.3]
    values = torch.tensor([[0.0, 0.5, 0.4, 0.2]])
    return cm, logps, ref, values


def test_kl_penalty_as_per_token_reward_k1_and_k3_and_gae_by_hand():
    cm, logps, ref, values = _one_row()
    cfg = ppo.PPOConfig(gamma=1.0, lam=1.0, whiten_advantages=False, kl_estimator="k1")
    out = ppo.advantages_and_returns(cfg, torch.tensor([1.0]), logps, ref, values, cm, kl_coef=0.5)
    # k1 = [0.1, -0.2, 0.3]; rewards = -0.5 * k1, + score 1 at the last token = [-0.05, 0.1, 0.85]
    torch.testing.assert_close(out["rewards"], torch.tensor([[0.0, -0.05, 0.1, 0.85]]))
    # gamma = lam = 1: returns are rewards-to-go [0.9, 0.95, 0.85]; advantages = returns - values
    torch.testing.assert_close(out["returns"], torch.tensor([[0.0, 0.9, 0.95, 0.85]]))
    torch.testing.assert_close(out["advantages"], torch.tensor([[0.0, 0.4, 0.55, 0.65]]))
    cfg.kl_estimator = "k3"  # k3 = exp(-d) + d - 1 for d = log pi - log ref
    k3 = [math.exp(-d) + d - 1 for d in (0.1, -0.2, 0.3)]
    out = ppo.advantages_and_returns(cfg, torch.tensor([1.0]), logps, ref, values, cm, kl_coef=0.5)
    torch.testing.assert_close(out["kl"], torch.tensor([[0.0, *k3]]))
    torch.testing.assert_close(out["rewards"], torch.tensor([[0.0, -0.5 * k3[0], -0.5 * k3[1], 1 - 0.5 * k3[2]]]))


def test_advantage_and_reward_whitening_flags():
    cm, logps, ref, values = _one_row()
    cm, logps, ref, values = (torch.cat([x, x]) for x in (cm, logps, ref, values))
    scores = torch.tensor([1.0, -2.0])
    cfg = ppo.PPOConfig(whiten_advantages=False, whiten_rewards=False)
    raw = ppo.advantages_and_returns(cfg, scores, logps, ref, values, cm, kl_coef=0.1)
    cfg.whiten_advantages = True
    white = ppo.advantages_and_returns(cfg, scores, logps, ref, values, cm, kl_coef=0.1)
    a = white["advantages"][cm]
    assert abs(float(a.mean())) < 1e-6 and float(a.std()) == pytest.approx(1.0, abs=1e-5)
    torch.testing.assert_close(white["returns"], raw["returns"])  # returns come from the raw advantages
    torch.testing.assert_close(a, (raw["advantages"][cm] - raw["advantages"][cm].mean()) / raw["advantages"][cm].std())
    cfg.whiten_rewards = True
    wr = ppo.advantages_and_returns(cfg, scores, logps, ref, values, cm, kl_coef=0.1)["rewards"][cm]
    r = raw["rewards"][cm]
    torch.testing.assert_close(wr, (r - r.mean()) / r.std() + r.mean())  # whitened, mean kept (TRL)


# ----------------------------------------------------------------------------- details 9, 10, 17: the losses
def test_entropy_bonus_and_value_clipping_flags():
    g = torch.Generator().manual_seed(0)
    cm = torch.tensor([[False, True, True], [False, True, False]])
    logps, old = -torch.rand(2, 3, generator=g), -torch.rand(2, 3, generator=g)
    ent, adv = torch.rand(2, 3, generator=g), torch.randn(2, 3, generator=g)
    base, _ = ppo.actor_loss(ppo.PPOConfig(entropy_coef=0.0), logps, ent, old, adv, cm)
    bonus, m = ppo.actor_loss(ppo.PPOConfig(entropy_coef=0.1), logps, ent, old, adv, cm)
    mean_ent = (ent[0, 1] + ent[0, 2] + ent[1, 1]) / 3
    assert m["entropy"] == pytest.approx(float(mean_ent))
    torch.testing.assert_close(bonus, base - 0.1 * mean_ent)

    values = torch.tensor([[0.0, 1.0, 2.0], [0.0, -1.0, 0.0]])
    old_v = torch.zeros(2, 3)
    ret = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])
    # clip 0.2: V_clip = [0.2, 0.2, -0.2]; per token max((V-R)^2, (Vc-R)^2) = [1, 2.25, 1]; loss = 0.5 * 4.25 / 3
    clipped, mc = ppo.critic_loss(ppo.PPOConfig(value_clip=0.2), values, old_v, ret, cm)
    assert float(clipped) == pytest.approx(0.5 * 4.25 / 3) and mc["value_clip_frac"] == 0.0
    plain, mp = ppo.critic_loss(ppo.PPOConfig(value_clip=0.0), values, old_v, ret, cm)
    assert float(plain) == pytest.approx(0.5 * 4.25 / 3) and mp["value_clip_frac"] == 0.0
    ret = torch.tensor([[0.0, 2.0, 0.5], [0.0, -1.0, 0.0]])  # targets far from the old values: clip binds
    clipped, mc = ppo.critic_loss(ppo.PPOConfig(value_clip=0.2), values, old_v, ret, cm)
    plain, _ = ppo.critic_loss(ppo.PPOConfig(value_clip=0.0), values, old_v, ret, cm)
    # unclipped: [1, 2.25, 0]; clipped V = [0.2, 0.2, -0.2] -> [3.24, 0.09, 0.64]; max = [3.24, 2.25, 0.64]
    assert float(plain) == pytest.approx(0.5 * 3.25 / 3)
    assert float(clipped) == pytest.approx(0.5 * (3.24 + 2.25 + 0.64) / 3)
    assert mc["value_clip_frac"] == pytest.approx(2 / 3)


# ----------------------------------------------------------------------------- details 11, 13, 14: models
def test_value_init_from_the_reward_model_or_the_policy(world):
    from posttrain.models import load_model, load_tokenizer
    from posttrain.scoring import left_pad, load_reward_model, reward_forward

    pad = load_tokenizer(world["sft"]).pad_token_id
    rm, _ = load_reward_model(world["rm"])
    v = ppo.build_value_model("reward", world["sft"], world["rm"], pad, 0, "cpu").eval()
    for k, w in rm.state_dict().items():
        assert torch.equal(v.state_dict()[k], w), k
    # values[:, t] is the reward model's score of the prefix before token t (the aligned-value convention)
    seqs = [[5, 9, 30, 31, 32, 33], [7, 8, 40, 41]]
    ids, am = left_pad(seqs, pad)
    with torch.no_grad():
        vals = ppo.token_values(v, ids, am)  # (2, 6)
        assert vals[0, 0] == 0.0
        for t in range(1, ids.shape[1]):  # row 0 is the longest: no padding, every prefix ends in a real token
            torch.testing.assert_close(vals[0, t], reward_forward(rm, ids[:1, :t], am[:1, :t])[0])
        # left padding does not change a row's values
        torch.testing.assert_close(vals[1, 3:], ppo.token_values(v, ids[1:, 2:], am[1:, 2:])[0, 1:])
        # rollout values in micro-batches grouped by length (rows 1, 3 then 0, 2): each row's values in its place
        seqs = [[5, 9, 30, 31, 32, 33, 34, 35], [7, 8], [6, 9, 30, 31, 32, 33, 34], [7, 40]]
        ids, am = left_pad(seqs, pad)
        one = SimpleNamespace(process_index=0, num_processes=1, unwrap_model=lambda m: m)
        got = ppo.rollout_values(one, ppo.TokenValueModel(v), SimpleNamespace(input_ids=ids, attention_mask=am,
                                                                                 completion_mask=am), 2)
        want = torch.cat([ppo.token_values(v, ids[i:i + 1], am[i:i + 1]) for i in range(len(seqs))]) * am
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    pv = ppo.build_value_model("policy", world["sft"], None, pad, 0, "cpu")
    sft = load_model(world["sft"]).state_dict()
    inner = pv.state_dict()
    for k, w in sft.items():
        if k.startswith("model."):
            assert torch.equal(inner[k], w), k
    assert not torch.equal(inner["score.weight"], rm.state_dict()["score.weight"])  # a new head
    with pytest.raises(Exception, match="value_init=reward needs a reward model"):
        ppo.build_value_model("reward", world["sft"], None, pad, 0, "cpu")


def test_disable_dropout_makes_train_mode_forwards_deterministic():
    from transformers import LlamaConfig, LlamaForCausalLM

    torch.manual_seed(0)
    model = LlamaForCausalLM(LlamaConfig(vocab_size=64, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                                         num_attention_heads=2, num_key_value_heads=2, attention_dropout=0.5,
                                         attn_implementation="eager"))
    model.train()
    ids = torch.randint(0, 64, (2, 10))
    assert not torch.equal(model(ids).logits, model(ids).logits)  # dropout active
    assert ppo.disable_dropout(model) >= 1 and model.config.attention_dropout == 0.0
    assert torch.equal(model(ids).logits, model(ids).logits)


def test_disable_dropout_flag_makes_the_first_ratio_exactly_one(world, tmp_path, vowels):
    """With dropout on, the update's forward (train mode) differs from the rollout-time one (eval mode)."""
    sft = tmp_path / "dropout-sft"
    shutil.copytree(world["sft"], sft)
    cfg = json.loads((sft / "config.json").read_text())
    cfg.update(attention_dropout=0.3, attn_implementation="eager")
    (sft / "config.json").write_text(json.dumps(cfg))
    kl = {}
    for flag in ("true", "false"):
        out = tmp_path / flag
        (out / "tiny-summarize" / "sft").mkdir(parents=True)
        shutil.copytree(sft, out / "tiny-summarize" / "sft" / "final")
        assert main(_args(world, out, f"disable_dropout={flag}", "max_steps=1", "ppo_epochs=1",
                          "minibatch_size=8")) == 0
        kl[flag] = _metrics(out)[0]["policy/approx_kl"]
    assert kl["true"] == 0.0 and kl["false"] > 1e-4, kl


def test_policy_loss_family_and_rollout_correction(world, tmp_path, vowels, monkeypatch, perturbed_sampler):
    """cispo and gspo_token give clip's loss and gradient on the first (on-policy) update; with a sampler whose
    log-probs are off by N(0, 0.7) the corrections bound or drop the policy loss's tokens."""
    def first(name: str, *extra: str) -> dict:
        out = tmp_path / name
        assert main(_args(world, out, "max_steps=1", "ppo_epochs=1", "minibatch_size=8", *extra)) == 0
        return _metrics(out)[0]

    clip = first("clip")
    for kind in ("cispo", "gspo_token"):
        m = first(kind, f"policy_loss={kind}")
        assert m["policy/loss"] == pytest.approx(clip["policy/loss"], rel=1e-4, abs=1e-6), kind
        assert m["policy/grad_norm"] == pytest.approx(clip["policy/grad_norm"], rel=1e-3), kind
    assert clip["mismatch/kl"] < 1e-6 and clip["mismatch/max_ratio"] == pytest.approx(1.0, abs=1e-4)
    monkeypatch.setattr(ppo, "generate", perturbed_sampler(ppo.generate, 0.7))
    tis = first("tis", "rollout_correction=tis")
    assert tis["mismatch/kl"] > 0.1 and tis["correction/max_weight"] <= 2.0 and tis["correction/truncated"] > 0.05
    mask = first("mask", "rollout_correction=mask")
    assert 0.05 < mask["correction/masked"] < 0.9 and mask["policy/grad_norm"] > 0


def test_log_probs_at_the_sampling_temperature(world):
    from posttrain.logprobs import batched_logprobs
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import SamplingParams, collate_rollouts, generate

    model, tok = load_model(world["sft"]), load_tokenizer(world["sft"])
    prompts = [r["prompt"] for r in summarize.make_examples(4, 0, "train")]
    batch = collate_rollouts(generate(model, tok, prompts, SamplingParams(temperature=0.7, max_new_tokens=10)),
                             tok.pad_token_id)
    cm = batch.completion_mask.bool()
    on = ppo.PPOConfig(temperature=0.7, scale_logits_by_temperature=True)
    off = ppo.PPOConfig(temperature=0.7, scale_logits_by_temperature=False)
    assert ppo.logprob_temperature(on) == 0.7 and ppo.logprob_temperature(off) == 1.0
    lp_on, _ = batched_logprobs(model, batch, temperature=ppo.logprob_temperature(on))
    lp_off, _ = batched_logprobs(model, batch, temperature=ppo.logprob_temperature(off))
    # on: the distribution the engine sampled from; off: the raw policy's (not what was sampled)
    torch.testing.assert_close(lp_on[cm], batch.logprobs[cm], atol=1e-4, rtol=0)
    torch.testing.assert_close(lp_off[cm], batch.policy_logprobs[cm], atol=1e-4, rtol=0)
    assert (lp_on[cm] - lp_off[cm]).abs().max() > 0.01


# ----------------------------------------------------------------------------- end to end
@pytest.mark.learning
def test_ppo_learns_a_hand_made_reward(world, tmp_path, vowels, capsys, learning):
    out = tmp_path / "learn"
    assert main(_args(world, out, f"task.train_file={world['short']}", "reward=rm", f"reward_model={world['rm']}",
                      "max_steps=12", "rollout_batch_size=32",
                      "minibatch_size=16", "ppo_epochs=4", "max_new_tokens=12", "lr=1e-2", "kl_coef=0.01",
                      "eval_every=6", "final_eval_rows=8", *learning.overrides)) == 0
    m = [r for r in _metrics(out) if "rollout/score_raw" in r]
    first, last = m[0]["rollout/score_raw"], sum(r["rollout/score_raw"] for r in m[-2:]) / 2
    learning.above("vowel fraction, last - first", last - first, 0.15, [r["rollout/score_raw"] for r in m])
    assert all(r["rollout/logprob_gap"] < 1e-3 for r in m)  # recomputed old log-probs == the engine's
    assert all(abs(r["mismatch/kl"]) < 1e-6 for r in m)  # fp32 sampler and trainer: no mismatch (k3 >= 0 up to rounding)
    evals = [r for r in _metrics(out) if "gold/win_rate" in r]
    assert [r["step"] for r in evals] == [0, 6, 12] and all("kl" in r for r in evals)
    text = capsys.readouterr().out
    assert "gold win-rate of the PPO model against the SFT model" in text
    run = out / "tiny-summarize" / "ppo"
    ev = json.loads((run / "eval.json").read_text())
    assert ev["sft"]["win_rate"] == 0.5 and 0.0 <= ev["ppo"]["win_rate"] <= 1.0
    from transformers import AutoModelForCausalLM

    assert AutoModelForCausalLM.from_pretrained(run / "final").config.vocab_size > 0


def test_fixed_kl_coefficient_stays_and_gold_reward_option_needs_no_reward_model(world, tmp_path):
    out = tmp_path / "gold"
    assert main(_args(world, out, "kl_coef=0.2", "reward_clip=0", "missing_eos_penalty=0", "temperature=0.7",
                      "save_rollouts_every=2")) == 0
    m = [r for r in _metrics(out) if "rollout/score_raw" in r]
    assert [r["kl_coef"] for r in m] == [0.2, 0.2]
    # rollout inspection: the iteration's samples, each with the reward it was trained on and its parts
    saved = [json.loads(l) for l in (out / "tiny-summarize" / "ppo" / "rollouts" / "step-000002.jsonl").read_text()
             .split("\n") if l]  # not splitlines: sampled text may hold \u2028
    extras = [json.loads(r["extras_json"]) for r in saved]
    assert len(saved) == 8 and all(r["prompt"] for r in saved)
    for r, e in zip(saved, extras):
        assert r["reward"] == pytest.approx(e["parts"]["score"] - e["parts"]["kl_penalty"], abs=1e-5)
        assert e["parts"]["score"] == pytest.approx(e["parts"]["score_raw"]) and "advantage" in e
    assert sum(e["parts"]["score_raw"] for e in extras) / 8 == pytest.approx(m[-1]["rollout/score_raw"], abs=1e-5)
    # detail 14 in the loop: old log-probs recomputed at T = 0.7 equal the engine's sampling log-probs
    assert all(r["rollout/logprob_gap"] < 1e-3 for r in m)
    assert all(r["rollout/score"] == pytest.approx(r["rollout/score_raw"]) for r in m)  # shaping off
    assert all(r["rollout/score_raw"] <= 1.0 for r in m)  # gold reward = quality (<= 1) - 2 * distance
    assert not (out / "tiny-summarize" / "rm").exists()


def test_gold_reward_on_another_task_logs_that_tasks_gold_metrics(tmp_path, capsys):
    """reward=gold on tiny-math: the evaluations log the task's GOLD_METRICS (gold/accuracy, gold/length_chars), not
    tiny-summarize's quality / in_band (whose keys the first evaluation used to look up: a KeyError), and the final
    comparison with the SFT model is written to eval.json."""
    from posttrain.models import bootstrap
    from posttrain.tasks import math as math_task

    out = tmp_path / "math"
    bootstrap("tiny", math_task.corpus(200, 0), out / "tiny-math" / "sft" / "final", vocab_size=384, seed=0,
              max_length=256, split_digits=True)  # the stage finds its "SFT model" and never runs SFT
    assert main(["ppo", "--recipe", "tiny-math", f"run.output_dir={out}", "reward=gold", "value_init=policy",
                 "rollout_batch_size=8", "minibatch_size=4", "ppo_epochs=1", "max_steps=2", "max_new_tokens=8",
                 "reward_norm=none", "eval_every=1", "eval_rows=4", "final_eval_rows=4", "save_every=0",
                 "task.n_train=32", "task.n_eval=8", "run.quiet=true", "run.threads=1"]) == 0
    run = out / "tiny-math" / "ppo"
    evals = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines() if "gold/win_rate" in l]
    assert [r["step"] for r in evals] == [0, 1, 2]
    for r in evals:
        assert {"gold/reward", "gold/accuracy", "gold/length_chars", "gold/win_rate", "kl"} <= set(r), r
        assert 0.0 <= r["gold/accuracy"] <= 1.0 and "gold/quality" not in r and "proxy/reward" not in r
    ev = json.loads((run / "eval.json").read_text())
    assert ev["sft"]["win_rate"] == 0.5 and 0.0 <= ev["ppo"]["accuracy"] <= 1.0 and len(ev["samples"]) == 4
    text = capsys.readouterr().out
    assert "accuracy" in text and "gold win-rate of the PPO model against the SFT model" in text
    assert (run / "final" / "config.json").is_file()


def test_reward_model_path_and_value_from_the_reward_model(world, tmp_path):
    out = tmp_path / "rm"
    assert main(_args(world, out, "reward=rm", f"reward_model={world['rm']}", "value_init=reward",
                      "missing_eos_penalty=2", "reward_clip=0", "eval_every=2")) == 0
    m = _metrics(out)
    assert any("proxy/reward" in r for r in m)  # the reward model is the proxy curve
    roll = [r for r in m if "rollout/no_eos" in r]
    # the EOS trick: with reward_norm=none and no clipping, score = raw - 2 for each completion that never ended
    assert any(r["rollout/no_eos"] > 0 for r in roll)  # a random model rarely says eos within 8 tokens
    assert all(r["rollout/score"] == pytest.approx(r["rollout/score_raw"] - 2 * r["rollout/no_eos"], abs=1e-4)
               for r in roll)


def test_injected_nan_stops_with_the_iteration_and_keeps_the_last_checkpoint(world, tmp_path, capsys, monkeypatch,
                                                                            vowels):
    calls = {"n": 0}
    real = ppo.losses.policy_loss

    def flaky(*a, **k):
        calls["n"] += 1
        loss, m = real(*a, **k)
        return (loss * float("nan") if calls["n"] == 3 else loss), m

    monkeypatch.setattr(ppo.losses, "policy_loss", flaky)
    out = tmp_path / "nan"
    assert main(_args(world, out, "max_steps=5", "ppo_epochs=1", "minibatch_size=8", "save_every=1",
                      "keep_checkpoints=10")) == 1
    err = capsys.readouterr().err
    ckpts = out / "tiny-summarize" / "ppo" / "checkpoints"
    assert "non-finite loss (nan) at step 3" in err and f"last good checkpoint: {ckpts / 'step-000002'}" in err
    assert sorted(p.name for p in ckpts.glob("step-*")) == ["step-000001", "step-000002"]
    state = torch.load(ckpts / "step-000002" / "state.pt", weights_only=False)
    assert all(torch.isfinite(v).all() for v in state["model"].values())
    assert not (out / "tiny-summarize" / "ppo" / "final").exists()


class Interrupted(Exception):
    pass


def test_resume_equals_an_uninterrupted_run(world, tmp_path, monkeypatch):
    """4 iterations in one go == a run killed during iteration 3, resumed from its iteration-2 checkpoint."""
    from safetensors.torch import load_file

    calls = {"n": 0, "kill_at": None}

    class Scorer(VowelScorer):
        def score(self, *a, **k):
            calls["n"] += 1
            if calls["n"] == calls["kill_at"]:
                raise Interrupted()
            return super().score(*a, **k)

    monkeypatch.setattr(ppo, "reward_scorer", lambda *a, **k: Scorer())
    common = ("max_steps=4", "save_every=2", "reward_norm=init", "reward_norm_prompts=8", "kl_control=adaptive",
              "kl_target=0.01", "kl_horizon=16", "schedule=linear")
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert main(_args(world, full, *common)) == 0
    calls.update(n=0, kill_at=4)  # scorer calls: 1 = reward normalisation, 2..5 = iterations 1..4
    with pytest.raises(Interrupted):
        main(_args(world, cut, *common))
    assert sorted(p.name for p in (cut / "tiny-summarize" / "ppo" / "checkpoints").glob("step-*")) == ["step-000002"]
    calls.update(n=0, kill_at=None)
    assert main(_args(world, cut, *common, "resume=true")) == 0
    assert calls["n"] == 2  # iterations 3 and 4 only: the normalisation statistics came from the checkpoint
    a = load_file(full / "tiny-summarize" / "ppo" / "final" / "model.safetensors")
    b = load_file(cut / "tiny-summarize" / "ppo" / "final" / "model.safetensors")
    for k in a:
        assert torch.allclose(a[k], b[k], atol=1e-6), k
    mf, mc = _metrics(full), _metrics(cut)
    assert [r["step"] for r in mc] == [1, 2, 3, 4]
    coefs = [r["kl_coef"] for r in mc]
    assert coefs[0] == 0.05 and coefs[-1] > coefs[0]  # adaptive: KL above the 0.01 target, the coefficient grows
    for rf, rc in zip(mf, mc):  # the same rollouts, rewards, KL coefficients and losses
        for k in ("rollout/score_raw", "kl_coef", "policy/loss", "value/loss"):
            assert rf[k] == pytest.approx(rc[k], rel=1e-5, abs=1e-7), k


@pytest.mark.learning
def test_lora_ppo_learns_with_no_reference_copy_and_saves_a_merged_model(world, tmp_path, vowels, capsys,
                                                                          monkeypatch, learning):
    """lora.enabled=true: the policy and the value model train adapters; the reference is the policy with its
    adapters off (load_model is called once: the policy; no reference copy is loaded), final/ is merged.

    The model: the random tiny model with its final norm weight set to 4. With the HF init (tied embeddings,
    std 0.02) no hidden state can give any token more than ~3% probability, and adapters on the transformer
    layers cannot touch the embeddings or the final norm, so they cannot move a random model's outputs far
    (measured: the best reachable vowel fraction is 0.17, and no_eos stays >= 0.7); full fine-tuning escapes
    by growing the embeddings. x4 gives the output layer the range of a trained model."""
    import posttrain.models as models

    sft = tmp_path / "lora" / "tiny-summarize" / "sft" / "final"
    model, tok = models.load_model(world["sft"]), models.load_tokenizer(world["sft"])
    with torch.no_grad():
        model.model.norm.weight.fill_(4.0)
    models.save_model(model, tok, sft)
    loads = []
    real_load = models.load_model
    monkeypatch.setattr(models, "load_model", lambda *a, **k: loads.append(a[0]) or real_load(*a, **k))
    out = tmp_path / "lora"
    assert main(_args(world, out, f"task.train_file={world['short']}", "reward=rm", f"reward_model={world['rm']}",
                      "max_steps=12", "rollout_batch_size=32", "minibatch_size=16", "ppo_epochs=4",
                      "max_new_tokens=24", "lr=5e-3", "kl_coef=0.01", "eval_every=4", "final_eval_rows=8",
                      "lora.enabled=true", *learning.overrides)) == 0
    text = capsys.readouterr().out
    assert "LoRA r=16" in text and "(policy)" in text and "(value model)" in text
    assert len(loads) == 1, loads  # the policy only: reference = adapters off
    m = [r for r in _metrics(out) if "rollout/score" in r]
    # The shaped score PPO maximises: vowel fraction - 1 for each completion that never ends (detail 3).
    first, last = m[0]["rollout/score"], sum(r["rollout/score"] for r in m[-2:]) / 2
    learning.above("shaped score, last - first", last - first, 0.5, [r["rollout/score"] for r in m])
    # The median of the last 4 iterations: one late iteration can spike back (at lr 1e-2, Zen 3, seed 0: no_eos
    # 0.0, 0.0, 0.0 then 0.84 at the last of 12) while the run as a whole has learned to end its completions.
    # lr 5e-3, not 1e-2: at 1e-2 some seeds stay stuck at no_eos ~1 for 8+ iterations (seed 2: score -0.78 until
    # iteration 8, last - first 0.08); at 5e-3 every seed 0-3 x threads 1, 2 learns (worst last - first 0.88,
    # worst no_eos 0.016: docs/results-archive.md, "Test margins").
    late = sorted(r["rollout/no_eos"] for r in m[-4:])
    learning.below("completions without EOS (median of the last 4 iterations)", (late[1] + late[2]) / 2, 0.3,
                   [r["rollout/no_eos"] for r in m])
    assert all(r["rollout/logprob_gap"] < 1e-3 for r in m)  # the engine's LoRA path == the policy's forward
    # the reference is the base: KL is 0 before the first update (fp32 rounding: the lean forward may run the policy's
    # and the reference's rows in different groupings) and grows once the adapters moved
    assert abs(m[0]["rollout/kl"]) < 1e-5, [r["rollout/kl"] for r in m]
    learning.above("KL to the reference at the end", m[-1]["rollout/kl"], 0.1, [r["rollout/kl"] for r in m])
    assert "gold win-rate of the PPO model against the SFT model" in text
    final = out / "tiny-summarize" / "ppo" / "final"
    assert not (final / "adapter_config.json").exists()
    merged, base = real_load(final), real_load(sft)
    base_w = base.state_dict()
    diff = {n: float((w - base_w[n]).abs().max()) for n, w in merged.state_dict().items()}
    assert diff["model.embed_tokens.weight"] == 0.0  # not adapted: untouched
    assert diff["model.layers.0.self_attn.q_proj.weight"] > 0  # adapted: base + B @ A merged in
