"""Numeric tests of posttrain.advantages: a hand-computed case per function, then properties."""
import math

import pytest
import torch

from posttrain import advantages as adv_mod
from posttrain.advantages import (
    AdaptiveKLController,
    FixedKLController,
    gae,
    group_advantages,
    rewards_with_kl,
    turn_rewards_with_kl,
    zero_variance_groups,
)

NAN = float("nan")


# ----------------------------------------------------------------------------- GAE
def test_gae_hand_computed_unequal_lengths():
    # RolloutBatch layout: column 0 is a prompt token, row 1 ends one column early (padding).
    # NaN in masked columns proves they are never read.
    mask = torch.tensor([[0, 1, 1, 1], [0, 1, 1, 0]], dtype=torch.bool)
    rewards = torch.tensor([[NAN, 0.0, 0.0, 1.0], [NAN, -0.1, 2.0, NAN]])
    values = torch.tensor([[NAN, 0.5, 0.4, 0.2], [NAN, 1.0, 0.5, NAN]])
    a, r = gae(rewards, values, mask, gamma=0.9, lam=0.5)  # gamma * lam = 0.45
    # row 0, backwards:
    #   t3: delta = 1 + 0.9*0 - 0.2 = 0.8                 A = 0.8
    #   t2: delta = 0 + 0.9*0.2 - 0.4 = -0.22             A = -0.22 + 0.45*0.8 = 0.14
    #   t1: delta = 0 + 0.9*0.4 - 0.5 = -0.14             A = -0.14 + 0.45*0.14 = -0.077
    # row 1 (last valid token t2, nothing bootstrapped from the padding):
    #   t2: delta = 2 - 0.5 = 1.5                         A = 1.5
    #   t1: delta = -0.1 + 0.9*0.5 - 1.0 = -0.65          A = -0.65 + 0.45*1.5 = 0.025
    torch.testing.assert_close(a, torch.tensor([[0.0, -0.077, 0.14, 0.8], [0.0, 0.025, 1.5, 0.0]]))
    # returns = A + V: [0.423, 0.54, 1.0], [1.025, 2.0]
    torch.testing.assert_close(r, torch.tensor([[0.0, 0.423, 0.54, 1.0], [0.0, 1.025, 2.0, 0.0]]))


def test_gae_lambda_one_gamma_one_is_reward_to_go_minus_value():
    g = torch.Generator().manual_seed(0)
    B, T = 3, 6
    lengths = torch.tensor([6, 4, 1])
    mask = torch.arange(T)[None, :] < lengths[:, None]  # right-padded
    rewards, values = torch.randn(B, T, generator=g), torch.randn(B, T, generator=g)
    a, r = gae(rewards, values, mask, gamma=1.0, lam=1.0)
    to_go = (rewards * mask).flip(-1).cumsum(-1).flip(-1)  # sum_{s >= t, valid} r_s
    torch.testing.assert_close(a, (to_go - values) * mask)
    torch.testing.assert_close(r, to_go * mask)  # returns = reward-to-go


def test_gae_lambda_zero_is_one_step_td_error():
    g = torch.Generator().manual_seed(1)
    rewards, values = torch.randn(2, 5, generator=g), torch.randn(2, 5, generator=g)
    mask = torch.tensor([[1, 1, 1, 1, 1], [1, 1, 1, 0, 0]], dtype=torch.bool)
    a, _ = gae(rewards, values, mask, gamma=0.8, lam=0.0)
    next_v = torch.cat([values[:, 1:] * mask[:, 1:], torch.zeros(2, 1)], dim=1)  # 0 after the last token
    torch.testing.assert_close(a, (rewards + 0.8 * next_v - values) * mask)


def test_gae_skips_holes_and_ignores_grad():
    # a masked column inside a completion is stepped over: same as the compacted row
    rewards = torch.tensor([[0.3, NAN, -0.2, 1.0]])
    values = torch.tensor([[0.1, NAN, 0.6, 0.2]], requires_grad=True)
    a, r = gae(rewards, values, torch.tensor([[1, 0, 1, 1]], dtype=torch.bool), gamma=0.7, lam=0.9)
    ac, rc = gae(rewards[:, [0, 2, 3]], values.detach()[:, [0, 2, 3]], torch.ones(1, 3, dtype=torch.bool), gamma=0.7, lam=0.9)
    torch.testing.assert_close(a[:, [0, 2, 3]], ac)
    torch.testing.assert_close(r[:, [0, 2, 3]], rc)
    assert a[0, 1] == 0 and r[0, 1] == 0
    assert not a.requires_grad and not r.requires_grad  # constants of the update


# ----------------------------------------------------------------------------- RLHF reward
def test_rewards_with_kl_hand_computed():
    mask = torch.tensor([[0, 1, 1, 1], [0, 1, 1, 0]], dtype=torch.bool)
    kl = torch.tensor([[9.0, 0.1, 0.2, 0.3], [9.0, 0.5, -0.2, 9.0]])
    score = torch.tensor([1.0, -2.0])
    r = rewards_with_kl(score, kl, mask, kl_coef=0.1)
    # -0.1 * KL at every completion token, + score at the last one:
    #   row 0: [0, -0.01, -0.02, -0.03 + 1 = 0.97];  row 1: [0, -0.05, +0.02 - 2 = -1.98, 0]
    torch.testing.assert_close(r, torch.tensor([[0.0, -0.01, -0.02, 0.97], [0.0, -0.05, -1.98, 0.0]]))
    # the total reward of a row is score - kl_coef * sum KL
    torch.testing.assert_close(r.sum(-1), score - 0.1 * (kl * mask).sum(-1))


def test_rewards_with_kl_rejects_empty_completion():
    with pytest.raises(ValueError, match="rows \\[1\\]"):
        rewards_with_kl(torch.zeros(2), torch.zeros(2, 3), torch.tensor([[1, 1, 0], [0, 0, 0]]), kl_coef=0.1)


# ----------------------------------------------------------------------------- multi-turn: turn rewards, GAE
# Row 0: a prompt column, turn 1 (columns 1-2), an environment token (3), turn 2 (4-5), padding (6).
# Row 1: one turn (columns 1-3), then padding. NaN wherever a column must never be read.
TURN_MASK = torch.tensor([[0, 1, 1, 0, 1, 1, 0], [0, 1, 1, 1, 0, 0, 0]], dtype=torch.bool)


def test_turn_rewards_with_kl_hand_computed():
    kl = torch.tensor([[NAN, 0.1, 0.2, NAN, 0.3, -0.1, NAN], [NAN, 0.2, 0.0, -0.2, NAN, NAN, NAN]])
    score = torch.tensor([1.0, -1.0])
    turns = torch.tensor([[0.5, 0.25], [2.0, 0.0]])  # row 1 has one turn: its second entry must be 0
    r = turn_rewards_with_kl(score, kl, TURN_MASK, turns, kl_coef=0.5)
    # -0.5 * KL at sampled tokens; turn k's reward at its last sampled token; the score at the very last one:
    #   row 0: [0, -0.05, -0.1 + 0.5, 0 (environment), -0.15, 0.05 + 0.25 + 1, 0]
    #   row 1: [0, -0.1, 0, 0.1 + 2 - 1, 0, 0, 0]
    torch.testing.assert_close(r, torch.tensor([[0.0, -0.05, 0.4, 0.0, -0.15, 1.3, 0.0],
                                                [0.0, -0.1, 0.0, 1.1, 0.0, 0.0, 0.0]]))
    # no turn rewards: exactly rewards_with_kl
    none = turn_rewards_with_kl(score, kl, TURN_MASK, torch.zeros(2, 2), kl_coef=0.5)
    torch.testing.assert_close(none, rewards_with_kl(score, kl, TURN_MASK, kl_coef=0.5))
    torch.testing.assert_close(turn_rewards_with_kl(score, kl, TURN_MASK, torch.zeros(2, 0), kl_coef=0.5), none)


def test_gae_over_turns_hand_computed():
    """GAE over the sampled tokens only (gamma 0.9, lambda 0.5): turn 1's last token bootstraps from the value
    at turn 2's first token; the environment column (NaN value and reward) is no time step."""
    kl = torch.tensor([[NAN, 0.1, 0.2, NAN, 0.3, -0.1, NAN], [NAN, 0.2, 0.0, -0.2, NAN, NAN, NAN]])
    rewards = turn_rewards_with_kl(torch.tensor([1.0, -1.0]), kl, TURN_MASK, torch.tensor([[0.5, 0.25], [2.0, 0.0]]),
                                   kl_coef=0.5)
    values = torch.tensor([[NAN, 0.5, 0.4, NAN, 0.2, 0.1, NAN], [NAN, 0.3, 0.2, 0.6, NAN, NAN, NAN]])
    rewards = torch.where(TURN_MASK, rewards, torch.full_like(rewards, NAN))  # gae must not read them either
    a, ret = gae(rewards, values, TURN_MASK, gamma=0.9, lam=0.5)  # gamma * lam = 0.45
    # row 0, backwards over columns 5, 4, 2, 1 (rewards 1.3, -0.15, 0.4, -0.05):
    #   t5: delta = 1.3 - 0.1 = 1.2                                       A = 1.2
    #   t4: delta = -0.15 + 0.9 * 0.1 - 0.2 = -0.26                       A = -0.26 + 0.45 * 1.2 = 0.28
    #   t2: delta = 0.4 + 0.9 * V(t4) 0.2 - 0.4 = 0.18 (not V(t3))        A = 0.18 + 0.45 * 0.28 = 0.306
    #   t1: delta = -0.05 + 0.9 * 0.4 - 0.5 = -0.19                       A = -0.19 + 0.45 * 0.306 = -0.0523
    # row 1 (columns 3, 2, 1; rewards 1.1, 0, -0.1):
    #   t3: delta = 1.1 - 0.6 = 0.5                                       A = 0.5
    #   t2: delta = 0 + 0.9 * 0.6 - 0.2 = 0.34                            A = 0.34 + 0.45 * 0.5 = 0.565
    #   t1: delta = -0.1 + 0.9 * 0.2 - 0.3 = -0.22                        A = -0.22 + 0.45 * 0.565 = 0.03425
    torch.testing.assert_close(a, torch.tensor([[0.0, -0.0523, 0.306, 0.0, 0.28, 1.2, 0.0],
                                                [0.0, 0.03425, 0.565, 0.5, 0.0, 0.0, 0.0]]))
    torch.testing.assert_close(ret, torch.tensor([[0.0, 0.4477, 0.706, 0.0, 0.48, 1.3, 0.0],
                                                  [0.0, 0.33425, 0.765, 1.1, 0.0, 0.0, 0.0]]))
    # the same as GAE over the compressed row (its sampled tokens only, mask all ones)
    cols = TURN_MASK[0].nonzero().flatten()
    ac, rc = gae(rewards[:1, cols], values[:1, cols], torch.ones(1, len(cols), dtype=torch.bool), gamma=0.9, lam=0.5)
    torch.testing.assert_close(a[:1, cols], ac)
    torch.testing.assert_close(ret[:1, cols], rc)


def test_turn_rewards_with_a_full_mask_and_a_turns_reward_only_moves_its_own_and_earlier_tokens():
    g = torch.Generator().manual_seed(3)
    B, T = 3, 9
    kl, values, score = torch.randn(B, T, generator=g), torch.randn(B, T, generator=g), torch.randn(B, generator=g)
    # mask all ones (one turn per row): the turn's reward adds to the score, and GAE is the plain one
    full = torch.ones(B, T, dtype=torch.bool)
    c = torch.tensor([[0.7], [-0.3], [0.0]])
    r = turn_rewards_with_kl(score, kl, full, c, kl_coef=0.1)
    torch.testing.assert_close(r, rewards_with_kl(score + c[:, 0], kl, full, kl_coef=0.1))
    # three turns: columns 0-1, 3-5, 7 (environment columns 2 and 6, padding 8); a reward of 1 on turn 2 changes
    # the advantages (GAE is linear in the rewards) by (gamma lam)^(steps to turn 2's end) at turns 1 and 2's
    # tokens, counting sampled tokens only, and not at all at turn 3's
    m = torch.tensor([[1, 1, 0, 1, 1, 1, 0, 1, 0]], dtype=torch.bool).expand(B, T)
    base = turn_rewards_with_kl(score, kl, m, torch.zeros(B, 3), kl_coef=0.1)
    bumped = turn_rewards_with_kl(score, kl, m, torch.tensor([[0.0, 1.0, 0.0]] * B), kl_coef=0.1)
    torch.testing.assert_close(bumped - base, torch.tensor([[0, 0, 0, 0, 0, 1.0, 0, 0, 0]] * B))
    gl = 0.8 * 0.6
    da = gae(bumped, values, m, gamma=0.8, lam=0.6)[0] - gae(base, values, m, gamma=0.8, lam=0.6)[0]
    expected = torch.tensor([[gl ** 4, gl ** 3, 0, gl ** 2, gl, 1.0, 0, 0, 0]] * B)
    torch.testing.assert_close(da, expected)


def test_turn_rewards_with_kl_rejects_a_reward_for_a_missing_turn():
    with pytest.raises(ValueError, match="rows \\[1\\] have rewards for more turns"):
        turn_rewards_with_kl(torch.zeros(2), torch.zeros(2, 7), TURN_MASK, torch.tensor([[0.0, 1.0], [0.0, 1.0]]),
                             kl_coef=0.1)
    with pytest.raises(ValueError, match="must be \\(B=2, K\\)"):
        turn_rewards_with_kl(torch.zeros(2), torch.zeros(2, 7), TURN_MASK, torch.zeros(2), kl_coef=0.1)


# ----------------------------------------------------------------------------- group advantages
# N = 6, K = 3: group 0 = [3, 0, 0] (mean 1, centred [2, -1, -1], unbiased std sqrt(6/2) = sqrt(3)),
#               group 1 = [4, 4, 4] (zero variance)
REWARDS = torch.tensor([3.0, 0.0, 0.0, 4.0, 4.0, 4.0])


def test_grpo_hand_computed():
    # group std: [2, -1, -1] / sqrt(3) = [1.1547005, -0.5773503, -0.5773503]; zero-variance group -> 0
    s3 = math.sqrt(3)
    torch.testing.assert_close(
        group_advantages(REWARDS, 3, estimator="grpo", std_scale="group"),
        torch.tensor([2 / s3, -1 / s3, -1 / s3, 0.0, 0.0, 0.0]), rtol=1e-5, atol=1e-6,
    )
    # none (Dr. GRPO): mean-centred only
    torch.testing.assert_close(
        group_advantages(REWARDS, 3, estimator="grpo", std_scale="none"), torch.tensor([2.0, -1.0, -1.0, 0.0, 0.0, 0.0])
    )
    # batch: std of the raw rewards, mean 2.5, deviations [.5, -2.5, -2.5, 1.5, 1.5, 1.5],
    # sum of squares 19.5, / 5 = 3.9, std 1.9748418 -> [1.0127394, -0.5063697, -0.5063697, 0, 0, 0]
    sb = math.sqrt(3.9)
    torch.testing.assert_close(
        group_advantages(REWARDS, 3, estimator="grpo", std_scale="batch"),
        torch.tensor([2 / sb, -1 / sb, -1 / sb, 0.0, 0.0, 0.0]), rtol=1e-5, atol=1e-6,
    )


def test_rloo_hand_computed():
    # r_i - mean of the others: 3 - (0+0)/2 = 3; 0 - (3+0)/2 = -1.5; -1.5; constant group -> 0
    torch.testing.assert_close(
        group_advantages(REWARDS, 3, estimator="rloo", std_scale="none"), torch.tensor([3.0, -1.5, -1.5, 0.0, 0.0, 0.0])
    )
    # / group std sqrt(3): [1.7320508, -0.8660254, -0.8660254]
    s3 = math.sqrt(3)
    torch.testing.assert_close(
        group_advantages(REWARDS, 3, estimator="rloo", std_scale="group"),
        torch.tensor([3 / s3, -1.5 / s3, -1.5 / s3, 0.0, 0.0, 0.0]), rtol=1e-5, atol=1e-6,
    )


def test_reinforce_pp_hand_computed():
    # K > 1 (w/ baseline): centred by group [2, -1, -1, 0, 0, 0] (batch mean 0),
    # std of the centred values sqrt(6/5) = 1.0954451 -> [1.8257419, -0.9128709, -0.9128709, 0, 0, 0]
    s = math.sqrt(1.2)
    torch.testing.assert_close(
        group_advantages(REWARDS, 3, estimator="reinforce_pp", std_scale="batch"),
        torch.tensor([2 / s, -1 / s, -1 / s, 0.0, 0.0, 0.0]), rtol=1e-5, atol=1e-6,
    )
    # K = 1: [1, 2, 3, 6] - mean 3 = [-2, -1, 0, 3], std sqrt(14/3) = 2.1602469
    s1 = math.sqrt(14 / 3)
    torch.testing.assert_close(
        group_advantages(torch.tensor([1.0, 2.0, 3.0, 6.0]), 1, estimator="reinforce_pp", std_scale="batch"),
        torch.tensor([-2 / s1, -1 / s1, 0.0, 3 / s1]), rtol=1e-5, atol=1e-6,
    )


def test_group_advantages_properties():
    g = torch.Generator().manual_seed(0)
    r = torch.randn(4 * 5, generator=g)  # 5 groups of K = 4
    # RLOO = K/(K-1) * mean-centred; GRPO/RLOO advantages sum to 0 in each group
    rloo = group_advantages(r, 4, estimator="rloo", std_scale="none")
    torch.testing.assert_close(rloo, 4 / 3 * group_advantages(r, 4, estimator="grpo", std_scale="none"))
    for est in ("grpo", "rloo"):
        for scale in ("group", "batch", "none"):
            a = group_advantages(r, 4, estimator=est, std_scale=scale).view(5, 4)
            torch.testing.assert_close(a.sum(1), torch.zeros(5), atol=1e-5, rtol=0)
    # GRPO group z-scores have unit (unbiased) std in every group
    z = group_advantages(r, 4, estimator="grpo", std_scale="group").view(5, 4)
    torch.testing.assert_close(z.std(1), torch.ones(5), rtol=1e-4, atol=0)
    # REINFORCE++ advantages have zero mean and unit std over the batch
    rpp = group_advantages(r, 4, estimator="reinforce_pp", std_scale="batch")
    assert rpp.mean().abs().item() < 1e-6 and rpp.std().item() == pytest.approx(1.0, rel=1e-4)
    # RLOO of a constant group is 0; GRPO of an all-constant batch is 0 without NaN
    const = torch.full((6,), 0.7)
    for est, scale in [("rloo", "none"), ("grpo", "group"), ("grpo", "batch"), ("reinforce_pp", "batch")]:
        a = group_advantages(const, 3, estimator=est, std_scale=scale)
        assert torch.isfinite(a).all() and a.abs().max().item() < 1e-6, (est, scale)


def test_group_advantages_rejects_bad_arguments():
    with pytest.raises(ValueError, match="group_size=4"):
        group_advantages(REWARDS, 4, estimator="grpo", std_scale="group")
    with pytest.raises(ValueError, match="std_scale='batch'"):
        group_advantages(REWARDS, 3, estimator="reinforce_pp", std_scale="group")
    with pytest.raises(ValueError, match="group_size >= 2"):
        group_advantages(REWARDS, 1, estimator="rloo", std_scale="none")
    with pytest.raises(ValueError, match="estimator"):
        group_advantages(REWARDS, 3, estimator="ppo", std_scale="none")


def test_zero_variance_groups():
    assert zero_variance_groups(REWARDS, 3).tolist() == [False, True]
    assert zero_variance_groups(torch.tensor([1.0, 1.0, 0.0, 1.0, 0.0, 0.0]), 2).tolist() == [True, False, True]
    with pytest.raises(ValueError):
        zero_variance_groups(REWARDS, 4)


# ----------------------------------------------------------------------------- KL controllers
def test_adaptive_kl_controller_hand_computed_and_direction():
    ctl = AdaptiveKLController(init_kl_coef=0.2, target=6.0, horizon=10000)
    ctl.update(current_kl=9.0, n_steps=256)
    # e = clip(9/6 - 1 = 0.5, -0.2, 0.2) = 0.2: 0.2 * (1 + 0.2 * 256/10000) = 0.2 * 1.00512
    assert ctl.value == pytest.approx(0.201024)
    ctl.update(current_kl=5.4, n_steps=1000)
    # e = 5.4/6 - 1 = -0.1: 0.201024 * (1 - 0.1 * 0.1) = 0.19901376
    assert ctl.value == pytest.approx(0.19901376)
    before = ctl.value
    ctl.update(current_kl=6.0, n_steps=1000)  # at target: unchanged
    assert ctl.value == pytest.approx(before)
    ctl.update(current_kl=100.0, n_steps=1000)  # above target: up
    assert ctl.value > before
    up = ctl.value
    ctl.update(current_kl=0.0, n_steps=1000)  # below target: down, by at most 20% per horizon
    assert up * (1 - 0.2 * 0.1) == pytest.approx(ctl.value)
    fresh = AdaptiveKLController(0.5, 6.0, 10000)
    fresh.load_state_dict(ctl.state_dict())
    assert fresh.value == ctl.value


def test_fixed_kl_controller():
    ctl = FixedKLController(0.05)
    ctl.update(100.0, 512)
    assert ctl.value == 0.05
    other = FixedKLController(1.0)
    other.load_state_dict(ctl.state_dict())
    assert other.value == 0.05


def test_module_has_no_second_masked_mean():
    # masked means / whitening live in posttrain.logprobs only
    assert not any(name.startswith(("masked", "whiten")) for name in vars(adv_mod))


# ----------------------------------------------------------------------------- curriculum
def test_track_pass_rates_hand_computed():
    rates, seen = torch.zeros(4), torch.zeros(4, dtype=torch.bool)
    r, s = adv_mod.track_pass_rates(rates, seen, torch.tensor([1, 3]), torch.tensor([0.25, 1.0]), decay=0.5)
    assert r.tolist() == [0.0, 0.25, 0.0, 1.0] and s.tolist() == [False, True, False, True]  # first sight: as seen
    assert rates.tolist() == [0.0] * 4 and not seen.any()  # inputs untouched
    # problem 1 again: 0.5 * 0.25 + 0.5 * 0.75 = 0.5; problem 3 twice in one step: 1 -> 0.5 -> 0.25
    r, s = adv_mod.track_pass_rates(r, s, torch.tensor([1, 3, 3]), torch.tensor([0.75, 0.0, 0.0]), decay=0.5)
    assert r.tolist() == [0.0, 0.5, 0.0, 0.25]
    r0, _ = adv_mod.track_pass_rates(r, s, torch.tensor([1]), torch.tensor([1.0]), decay=0.0)
    assert r0[1].item() == 1.0  # decay 0: only the latest group
    with pytest.raises(ValueError, match="decay"):
        adv_mod.track_pass_rates(r, s, torch.tensor([1]), torch.tensor([1.0]), decay=1.0)


def test_curriculum_weights_hand_computed():
    rates = torch.tensor([0.5, 0.0, 1.0, 0.9, 0.3])
    seen = torch.tensor([True, True, True, True, False])
    w = adv_mod.curriculum_weights(rates, seen, 2, floor=0.05)
    # K = 2: 1 - p^2 - (1-p)^2 = 2 p (1 - p): 0.5, 0 -> floor, 0 -> floor, 0.18; unseen: 1
    torch.testing.assert_close(w, torch.tensor([0.5, 0.05, 0.05, 0.18, 1.0]))
    w8 = adv_mod.curriculum_weights(rates, seen, 8, floor=0.01)
    # K = 8 at p = 0.5: 1 - 2 / 256; at p = 0.9: 1 - 0.9^8 - 0.1^8 = 0.5695328
    assert w8[0].item() == pytest.approx(1 - 2 / 256) and w8[3].item() == pytest.approx(1 - 0.9 ** 8 - 0.1 ** 8)
    # the weight is the exact probability that a group of K Bernoulli(p) rewards is not all equal
    g = torch.Generator().manual_seed(0)
    draws = torch.rand(200_000, 8, generator=g) < 0.9
    informative = (draws.any(-1) & ~draws.all(-1)).float().mean().item()
    assert informative == pytest.approx(w8[3].item(), abs=0.005)
    with pytest.raises(ValueError, match="floor"):
        adv_mod.curriculum_weights(rates, seen, 2, floor=0.0)
