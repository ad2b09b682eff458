"""Numeric tests of posttrain.losses: a hand-computed case per function, then properties."""
import math

import pytest
import torch

from posttrain import losses

LOG2 = math.log(2.0)


def _sig(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


# ----------------------------------------------------------------------------- DPO
# Two pairs, beta = 0.5:
#   pair 1: pi_c=-1, pi_r=-3, ref_c=-2, ref_r=-2 -> chosen log-ratio 1, rejected -1, h = 2,  beta h = 1
#   pair 2: pi_c=-2, pi_r=-1, ref_c=-1, ref_r=-1 -> chosen log-ratio -1, rejected 0, h = -1, beta h = -0.5
PAIRS = dict(
    policy_chosen_logps=torch.tensor([-1.0, -2.0]),
    policy_rejected_logps=torch.tensor([-3.0, -1.0]),
    ref_chosen_logps=torch.tensor([-2.0, -1.0]),
    ref_rejected_logps=torch.tensor([-2.0, -1.0]),
)


def test_dpo_sigmoid_hand_computed():
    loss, m = losses.dpo_loss(**PAIRS, beta=0.5, loss_type="sigmoid")
    # -log sigmoid(x) = log(1 + e^-x): (log(1+e^-1) + log(1+e^0.5)) / 2 = (0.31326169 + 0.97407698) / 2
    assert loss.item() == pytest.approx((math.log1p(math.exp(-1.0)) + math.log1p(math.exp(0.5))) / 2)
    assert loss.item() == pytest.approx(0.64366934, abs=1e-7)
    # implicit rewards beta*(pi - ref): chosen [0.5, -0.5], rejected [-0.5, 0]
    assert m["rewards/chosen"] == pytest.approx(0.0)
    assert m["rewards/rejected"] == pytest.approx(-0.25)
    assert m["rewards/margin"] == pytest.approx(0.25)  # mean([1.0, -0.5])
    assert m["rewards/accuracy"] == pytest.approx(0.5)  # 0.5 > -0.5 yes, -0.5 > 0 no
    assert m["logps/chosen"] == pytest.approx(-1.5)
    assert m["logps/rejected"] == pytest.approx(-2.0)
    assert all(isinstance(v, float) for v in m.values())


def test_dpo_label_smoothing_hand_computed():
    one = {k: v[:1] for k, v in PAIRS.items()}  # pair 1, beta h = 1
    loss, _ = losses.dpo_loss(**one, beta=0.5, loss_type="sigmoid", label_smoothing=0.1)
    # -(0.9) log sig(1) - 0.1 log sig(-1) = 0.9 * 0.31326169 + 0.1 * 1.31326169 = 0.41326169
    assert loss.item() == pytest.approx(0.9 * math.log1p(math.exp(-1)) + 0.1 * math.log1p(math.exp(1)))
    assert loss.item() == pytest.approx(0.41326169, abs=1e-7)


def test_dpo_ipo_and_hinge_hand_computed():
    ipo, _ = losses.dpo_loss(**PAIRS, beta=0.5, loss_type="ipo")
    # target 1/(2 beta) = 1: ((2 - 1)^2 + (-1 - 1)^2) / 2 = (1 + 4) / 2
    assert ipo.item() == pytest.approx(2.5)
    hinge, _ = losses.dpo_loss(**PAIRS, beta=0.5, loss_type="hinge")
    # relu(1 - beta h): (relu(1 - 1) + relu(1 + 0.5)) / 2 = (0 + 1.5) / 2
    assert hinge.item() == pytest.approx(0.75)


@pytest.mark.parametrize("beta", [0.1, 0.5, 2.0])
def test_dpo_policy_equal_to_reference(beta):
    g = torch.Generator().manual_seed(0)
    c, r = -5 * torch.rand(8, generator=g), -5 * torch.rand(8, generator=g)
    kw = dict(policy_chosen_logps=c, policy_rejected_logps=r, ref_chosen_logps=c.clone(), ref_rejected_logps=r.clone())
    assert losses.dpo_loss(**kw, beta=beta, loss_type="sigmoid")[0].item() == pytest.approx(LOG2)
    assert losses.dpo_loss(**kw, beta=beta, loss_type="sigmoid", label_smoothing=0.3)[0].item() == pytest.approx(LOG2)
    assert losses.dpo_loss(**kw, beta=beta, loss_type="ipo")[0].item() == pytest.approx(1 / (4 * beta**2))
    assert losses.dpo_loss(**kw, beta=beta, loss_type="hinge")[0].item() == pytest.approx(1.0)


def test_dpo_label_smoothing_properties():
    g = torch.Generator().manual_seed(1)
    kw = {k: -3 * torch.rand(6, generator=g) for k in PAIRS}
    swapped = dict(
        policy_chosen_logps=kw["policy_rejected_logps"], policy_rejected_logps=kw["policy_chosen_logps"],
        ref_chosen_logps=kw["ref_rejected_logps"], ref_rejected_logps=kw["ref_chosen_logps"],
    )
    # eps = 0.5: blind to the label (swapping chosen and rejected changes nothing)
    a = losses.dpo_loss(**kw, beta=0.7, loss_type="sigmoid", label_smoothing=0.5)[0]
    b = losses.dpo_loss(**swapped, beta=0.7, loss_type="sigmoid", label_smoothing=0.5)[0]
    assert a.item() == pytest.approx(b.item())
    # L_eps(h) = (1 - eps) L_0(h) + eps L_0(-h), per pair, hence for the means
    l0 = losses.dpo_loss(**kw, beta=0.7, loss_type="sigmoid")[0]
    l0_swapped = losses.dpo_loss(**swapped, beta=0.7, loss_type="sigmoid")[0]
    leps = losses.dpo_loss(**kw, beta=0.7, loss_type="sigmoid", label_smoothing=0.2)[0]
    assert leps.item() == pytest.approx(0.8 * l0.item() + 0.2 * l0_swapped.item())


def test_dpo_gradient_by_hand():
    kw = {k: v.clone().requires_grad_(True) for k, v in PAIRS.items()}
    loss, _ = losses.dpo_loss(**kw, beta=0.5, loss_type="sigmoid")
    loss.backward()
    # d/d pi_c_i = -beta * sigmoid(-beta h_i) / B, beta h = [1, -0.5], B = 2
    expected = torch.tensor([-0.5 * _sig(-1.0) / 2, -0.5 * _sig(0.5) / 2])  # [-0.06723536, -0.15561483]
    torch.testing.assert_close(kw["policy_chosen_logps"].grad, expected)
    torch.testing.assert_close(kw["policy_rejected_logps"].grad, -expected)
    torch.testing.assert_close(kw["ref_chosen_logps"].grad, -expected)


def test_dpo_rejects_bad_arguments():
    with pytest.raises(ValueError, match="label_smoothing"):
        losses.dpo_loss(**PAIRS, beta=0.5, loss_type="ipo", label_smoothing=0.1)
    with pytest.raises(ValueError, match="label_smoothing"):
        losses.dpo_loss(**PAIRS, beta=0.5, loss_type="sigmoid", label_smoothing=0.7)
    with pytest.raises(ValueError, match="loss_type"):
        losses.dpo_loss(**PAIRS, beta=0.5, loss_type="kto")
    with pytest.raises(ValueError, match="beta"):
        losses.dpo_loss(**PAIRS, beta=0.0, loss_type="sigmoid")


# ----------------------------------------------------------------------------- Bradley-Terry
def test_simpo_hand_computed_and_gradient():
    # pair 1: chosen -4 over 2 tokens (mean -2), rejected -9 over 3 (mean -3); pair 2: chosen -3 over 1, rejected -2
    # over 2 (means -3 and -1). beta 2, gamma 0.5: rewards -4 / -6 and -6 / -2, arguments 2 - 0.5 = 1.5 and -4.5
    pc = torch.tensor([-4.0, -3.0], requires_grad=True)
    pr = torch.tensor([-9.0, -2.0], requires_grad=True)
    nc, nr = torch.tensor([2.0, 1.0]), torch.tensor([3.0, 2.0])
    loss, m = losses.simpo_loss(pc, pr, nc, nr, beta=2.0, gamma=0.5)
    assert loss.item() == pytest.approx((math.log1p(math.exp(-1.5)) + math.log1p(math.exp(4.5))) / 2)
    assert loss.item() == pytest.approx(2.3562305, abs=1e-6)  # (0.2014133 + 4.5110476) / 2
    assert m["rewards/chosen"] == pytest.approx(-5.0) and m["rewards/rejected"] == pytest.approx(-4.0)
    assert m["rewards/margin"] == pytest.approx(-1.0) and m["rewards/accuracy"] == pytest.approx(0.5)
    assert m["logps/chosen"] == pytest.approx(-2.5) and m["logps/rejected"] == pytest.approx(-2.0)
    loss.backward()
    # d/d log pi(y_c) = -sigmoid(-z) * beta / |y_c| / B; d/d log pi(y_r) = +sigmoid(-z) * beta / |y_r| / B
    s1, s2 = _sig(-1.5), _sig(4.5)
    torch.testing.assert_close(pc.grad, torch.tensor([-s1 * 2 / 2 / 2, -s2 * 2 / 1 / 2]))
    torch.testing.assert_close(pr.grad, torch.tensor([s1 * 2 / 3 / 2, s2 * 2 / 2 / 2]))
    # no reference, and a longer side is not favoured: doubling a side's tokens and log-prob changes nothing
    again, _ = losses.simpo_loss(pc * 2, pr, nc * 2, nr, beta=2.0, gamma=0.5)
    assert again.item() == pytest.approx(loss.item())
    with pytest.raises(ValueError, match="gamma"):
        losses.simpo_loss(pc, pr, nc, nr, beta=2.0, gamma=-1.0)


def test_orpo_hand_computed_and_gradient():
    # chosen: 2 tokens of probability 0.5 (mean log-prob log 0.5: odds 1, log-odds 0); rejected: 3 tokens of 0.2
    # (odds 0.25, log-odds log 0.25). Log-odds ratio log 4; L_OR = log(1 + 1/4); L_SFT = log 2; lambda 0.1
    pc = torch.tensor([2 * math.log(0.5)], requires_grad=True)
    pr = torch.tensor([3 * math.log(0.2)], requires_grad=True)
    loss, m = losses.orpo_loss(pc, pr, torch.tensor([2.0]), torch.tensor([3.0]), lam=0.1)
    assert loss.item() == pytest.approx(LOG2 + 0.1 * math.log(1.25))
    assert loss.item() == pytest.approx(0.7154616, abs=1e-6)
    assert m["nll"] == pytest.approx(LOG2) and m["odds_ratio_loss"] == pytest.approx(math.log(1.25))
    assert m["log_odds_ratio"] == pytest.approx(math.log(4.0)) and m["rewards/accuracy"] == 1.0
    assert m["rewards/margin"] == pytest.approx(0.1 * math.log(4.0))
    loss.backward()
    # l = log pi / n; d log-odds / d l = 1 / (1 - P); dL_OR / d(ratio) = -sigmoid(-ratio) = -1/5
    # chosen: (-1 (NLL) + 0.1 * -0.2 * 1 / (1 - 0.5)) / 2 tokens; rejected: 0.1 * 0.2 * 1 / (1 - 0.2) / 3 tokens
    assert pc.grad.item() == pytest.approx((-1 - 0.1 * 0.2 * 2) / 2)
    assert pr.grad.item() == pytest.approx(0.1 * 0.2 * 1.25 / 3)
    zero, _ = losses.orpo_loss(pc, pr, torch.tensor([2.0]), torch.tensor([3.0]), lam=0.0)
    assert zero.item() == pytest.approx(LOG2)  # lambda 0: plain SFT on the chosen side
    # a near-certain side (mean log-prob 0) stays finite
    sure, _ = losses.orpo_loss(torch.tensor([0.0]), pr.detach(), torch.tensor([2.0]), torch.tensor([3.0]), lam=0.1)
    assert math.isfinite(sure.item())


def test_bradley_terry_hand_computed_and_gradient():
    rc = torch.tensor([2.0, 0.0], requires_grad=True)
    rr = torch.tensor([1.0, 1.0])
    loss, m = losses.bradley_terry_loss(rc, rr)
    # diffs [1, -1]: (log(1+e^-1) + log(1+e^1)) / 2 = (0.31326169 + 1.31326169) / 2
    assert loss.item() == pytest.approx(0.81326169, abs=1e-7)
    assert m == pytest.approx({"accuracy": 0.5, "margin": 0.0, "reward/chosen": 1.0, "reward/rejected": 1.0})
    loss.backward()
    # d/d r_c_i = -sigmoid(-(r_c - r_r)_i) / B
    torch.testing.assert_close(rc.grad, torch.tensor([-_sig(-1.0) / 2, -_sig(1.0) / 2]))
    # with a required margin of 0.5: logits [0.5, -1.5]: (log(1+e^-0.5) + log(1+e^1.5)) / 2
    lm, mm = losses.bradley_terry_loss(rc.detach(), rr, margin=torch.tensor([0.5, 0.5]))
    assert lm.item() == pytest.approx((math.log1p(math.exp(-0.5)) + math.log1p(math.exp(1.5))) / 2)
    assert lm.item() == pytest.approx(1.08774513, abs=1e-7)
    assert mm["margin"] == 0.0  # the logged margin is r_c - r_r, without the required one


def test_bradley_terry_equal_rewards_is_log2():
    r = torch.randn(5)
    assert losses.bradley_terry_loss(r, r.clone())[0].item() == pytest.approx(LOG2)


# ----------------------------------------------------------------------------- PPO policy loss
def _ppo_case():
    """B=2, T=4; column 0 is a prompt token, row 1 has one completion token then padding.

    row 0: ratios [1.5, 0.5, 0.5], A [+1, +1, -2];  row 1: ratio [1.1], A [+3].
    Padding / prompt columns hold NaN: they must never reach the loss or its gradient.
    """
    nan = float("nan")
    completion_mask = torch.tensor([[0, 1, 1, 1], [0, 1, 0, 0]], dtype=torch.bool)
    old = torch.full((2, 4), -1.0)
    ratios = torch.tensor([[1.0, 1.5, 0.5, 0.5], [1.0, 1.1, 1.0, 1.0]])
    logps = old + ratios.log()
    logps[~completion_mask] = nan
    adv = torch.tensor([[nan, 1.0, 1.0, -2.0], [nan, 3.0, nan, nan]])
    return logps.requires_grad_(True), old, adv, completion_mask


def test_ppo_policy_loss_hand_computed():
    logps, old, adv, mask = _ppo_case()
    # per-token max(-A r, -A clip(r, 0.8, 1.2)):
    #   r=1.5,A=+1: max(-1.5, -1.2) = -1.2  (clipped, high)
    #   r=0.5,A=+1: max(-0.5, -0.8) = -0.5  (unclipped)
    #   r=0.5,A=-2: max(+1.0, +1.6) = +1.6  (clipped, low)
    #   r=1.1,A=+3: max(-3.3, -3.3) = -3.3  (inside the range)
    loss, m = losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2)
    assert loss.item() == pytest.approx((-1.2 - 0.5 + 1.6 - 3.3) / 4)  # token_mean = -0.85
    loss_seq, _ = losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2, aggregation="seq_mean_token_mean")
    assert loss_seq.item() == pytest.approx(((-1.2 - 0.5 + 1.6) / 3 + (-3.3)) / 2)  # -1.6666667
    loss_dr, _ = losses.ppo_policy_loss(
        logps, old, adv, mask, clip_eps=0.2, aggregation="seq_mean_token_sum_norm", max_tokens=5
    )
    assert loss_dr.item() == pytest.approx(-3.4 / (2 * 5))  # -0.34
    assert m["clip_frac"] == pytest.approx(0.5)
    assert m["clip_frac_high"] == pytest.approx(0.25)
    assert m["clip_frac_low"] == pytest.approx(0.25)
    assert m["ratio_mean"] == pytest.approx((1.5 + 0.5 + 0.5 + 1.1) / 4)  # 0.9
    assert m["ratio_max"] == pytest.approx(1.5)
    # k3 = r - 1 - log r: 0.0945349 + 2 * 0.1931472 + 0.0046898 = 0.4855190, / 4
    k3 = sum(r - 1 - math.log(r) for r in (1.5, 0.5, 0.5, 1.1)) / 4
    assert m["approx_kl"] == pytest.approx(k3)
    assert m["approx_kl"] == pytest.approx(0.1213797, abs=1e-6)


def test_ppo_policy_loss_gradient_by_hand():
    logps, old, adv, mask = _ppo_case()
    loss, _ = losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2)
    loss.backward()
    # token_mean over n=4 tokens: d/d logp = d(-A r)/d logp / 4 = -A r / 4 where unclipped, 0 where clipped
    expected = torch.tensor([[0.0, 0.0, -1.0 * 0.5 / 4, 0.0], [0.0, -3.0 * 1.1 / 4, 0.0, 0.0]])
    torch.testing.assert_close(logps.grad, expected)  # finite everywhere despite the NaN padding


def test_ppo_clip_higher_changes_only_positive_advantages_above_one_plus_eps_low():
    g = torch.Generator().manual_seed(0)
    B, T = 4, 6
    old = -2 * torch.rand(B, T, generator=g)
    ratios = 0.5 + 1.1 * torch.rand(B, T, generator=g)  # in [0.5, 1.6]
    logps = old + ratios.log()
    adv = torch.randn(B, T, generator=g)
    changed = 0
    for i in range(B):
        for t in range(T):
            only = torch.zeros(B, T, dtype=torch.bool)
            only[i, t] = True  # the loss of one token
            sym, _ = losses.ppo_policy_loss(logps, old, adv, only, clip_eps=0.2)
            high, mh = losses.ppo_policy_loss(logps, old, adv, only, clip_eps=0.2, clip_eps_high=0.28)
            should_change = adv[i, t] > 0 and ratios[i, t] > 1.2
            assert (not torch.isclose(sym, high)) == bool(should_change), (i, t, ratios[i, t], adv[i, t])
            changed += int(should_change)
            if adv[i, t] > 0 and ratios[i, t] > 1.28:
                assert mh["clip_frac_high"] == 1.0
    assert changed > 0  # the case occurred


def test_ppo_aggregations_on_unequal_lengths():
    old = torch.zeros(2, 4)
    logps = torch.zeros(2, 4)  # ratio 1 everywhere: per-token loss = -A
    adv = torch.tensor([[1.0, 1.0, 1.0, 1.0], [4.0, 0.0, 0.0, 0.0]])
    unequal = torch.tensor([[1, 1, 1, 1], [1, 0, 0, 0]], dtype=torch.bool)

    def agg(mask, kind, max_tokens=None):
        return losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2, aggregation=kind, max_tokens=max_tokens)[0].item()

    # token mean: (4 * -1 + -4) / 5 = -1.6;  sequence mean: (-1 + -4) / 2 = -2.5;  Dr. GRPO: -8 / (2 * 8) = -0.5
    assert agg(unequal, "token_mean") == pytest.approx(-1.6)
    assert agg(unequal, "seq_mean_token_mean") == pytest.approx(-2.5)
    assert agg(unequal, "seq_mean_token_sum_norm", 8) == pytest.approx(-0.5)
    # equal lengths: token mean == sequence mean, and Dr. GRPO with max_tokens = T is the same too
    equal = torch.ones(2, 4, dtype=torch.bool)
    assert agg(equal, "token_mean") == pytest.approx(agg(equal, "seq_mean_token_mean"))
    assert agg(equal, "seq_mean_token_sum_norm", 4) == pytest.approx(agg(equal, "token_mean"))
    # Dr. GRPO's normaliser does not depend on the lengths: adding a zero-loss token changes nothing
    longer = unequal.clone()
    longer[1, 1] = True
    assert agg(longer, "seq_mean_token_sum_norm", 8) == pytest.approx(-0.5)
    assert agg(longer, "seq_mean_token_mean") != pytest.approx(-2.5)


def test_ppo_sequence_advantages_broadcast_and_errors():
    logps, old, adv, mask = _ppo_case()
    seq_adv = torch.tensor([1.0, -2.0])
    a, _ = losses.ppo_policy_loss(logps, old, seq_adv, mask, clip_eps=0.2)
    b, _ = losses.ppo_policy_loss(logps, old, seq_adv[:, None].expand(2, 4), mask, clip_eps=0.2)
    assert a.item() == pytest.approx(b.item())
    with pytest.raises(ValueError, match="max_tokens"):
        losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2, aggregation="seq_mean_token_sum_norm")
    with pytest.raises(ValueError, match="aggregation"):
        losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2, aggregation="sum")


def test_ppo_on_policy_loss_is_minus_mean_advantage():
    # first minibatch of an on-policy update: ratio = 1, nothing clipped, loss = -mean(A)
    g = torch.Generator().manual_seed(3)
    logps = -torch.rand(3, 5, generator=g)
    adv = torch.randn(3, 5, generator=g)
    mask = torch.ones(3, 5, dtype=torch.bool)
    loss, m = losses.ppo_policy_loss(logps, logps.clone(), adv, mask, clip_eps=0.2, clip_eps_high=0.3)
    assert loss.item() == pytest.approx(-adv.mean().item(), abs=1e-6)
    assert m["clip_frac"] == 0.0 and m["approx_kl"] == pytest.approx(0.0, abs=1e-7) and m["ratio_max"] == 1.0


# ----------------------------------------------------------------------------- KL estimators
def test_kl_penalty_hand_computed():
    logps = torch.tensor([[math.log(0.5), math.log(0.25)]])
    ref = torch.tensor([[math.log(0.25), math.log(0.5)]])
    # token 0: log pi - log ref = log 2 = 0.6931472; token 1: -log 2
    torch.testing.assert_close(losses.kl_penalty(logps, ref, "k1"), torch.tensor([[LOG2, -LOG2]]))
    # k2 = 1/2 (log 2)^2 = 0.2402265 for both
    torch.testing.assert_close(losses.kl_penalty(logps, ref, "k2"), torch.tensor([[0.5 * LOG2**2] * 2]))
    # k3 = r - 1 - log r, r = ref/pi: token 0: 0.5 - 1 + log 2 = 0.1931472; token 1: 2 - 1 - log 2 = 0.3068528
    torch.testing.assert_close(losses.kl_penalty(logps, ref, "k3"), torch.tensor([[LOG2 - 0.5, 1 - LOG2]]))
    with pytest.raises(ValueError, match="kind"):
        losses.kl_penalty(logps, ref, "k4")


def test_kl_penalty_expectations_and_gradients_match_exact_kl():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(7, generator=g, requires_grad=True)
    logq = torch.log_softmax(torch.randn(7, generator=g), -1)  # the reference
    logp = torch.log_softmax(logits, -1)
    p = logp.exp()
    kl_pq = (p * (logp - logq)).sum()
    # exact expectations over the vocabulary (no sampling): E_p[k1] = E_p[k3] = KL(p || q); k2, k3 >= 0
    for kind in ("k1", "k3"):
        assert (p * losses.kl_penalty(logp, logq, kind)).sum().item() == pytest.approx(kl_pq.item(), rel=1e-5)
    assert (losses.kl_penalty(logp, logq, "k2") >= 0).all() and (losses.kl_penalty(logp, logq, "k3") >= 0).all()
    for kind in ("k1", "k2", "k3"):
        assert losses.kl_penalty(logq, logq, kind).abs().max().item() == 0.0
    # as a loss on samples from p (weights p detached): grad E[k2] = grad KL(p||q), grad E[k3] = grad KL(q||p)
    grad_k2 = torch.autograd.grad((p.detach() * losses.kl_penalty(logp, logq, "k2")).sum(), logits, retain_graph=True)[0]
    grad_k3 = torch.autograd.grad((p.detach() * losses.kl_penalty(logp, logq, "k3")).sum(), logits, retain_graph=True)[0]
    grad_kl_pq = torch.autograd.grad(kl_pq, logits, retain_graph=True)[0]
    grad_kl_qp = torch.autograd.grad((logq.exp() * (logq - logp)).sum(), logits)[0]
    torch.testing.assert_close(grad_k2, grad_kl_pq)
    torch.testing.assert_close(grad_k3, grad_kl_qp)


# ----------------------------------------------------------------------------- value loss
def _value_case():
    """B=1, T=4, column 0 is a prompt column (NaN there must be ignored)."""
    nan = float("nan")
    mask = torch.tensor([[0, 1, 1, 1]], dtype=torch.bool)
    values = torch.tensor([[nan, 1.0, 2.0, 0.5]], requires_grad=True)
    old = torch.tensor([[nan, 0.5, 2.5, 0.4]])
    returns = torch.tensor([[nan, 2.0, 2.0, 1.0]])
    return values, old, returns, mask


def test_value_loss_hand_computed_and_gradient():
    values, old, returns, mask = _value_case()
    loss, m = losses.value_loss(values, old, returns, mask, clip_range=0.2)
    # t1: V=1.0, old 0.5 -> V_clip 0.7: max((1-2)^2, (0.7-2)^2) = max(1, 1.69) = 1.69  (clipped)
    # t2: V=2.0, old 2.5 -> V_clip 2.3: max(0, 0.09) = 0.09                            (clipped)
    # t3: V=0.5, old 0.4 -> V_clip 0.5: max(0.25, 0.25) = 0.25
    # 1/2 * (1.69 + 0.09 + 0.25) / 3 = 0.3383333
    assert loss.item() == pytest.approx(0.5 * (1.69 + 0.09 + 0.25) / 3)
    assert m["value_clip_frac"] == pytest.approx(2 / 3)
    # returns [2, 2, 1]: var 2/9; residuals R - V = [1, 0, 0.5]: var 1/6; EV = 1 - (1/6)/(2/9) = 0.25
    assert m["explained_variance"] == pytest.approx(0.25)
    assert m["value_mean"] == pytest.approx(3.5 / 3)
    loss.backward()
    # clipped branches are flat in V (clamp saturated); t3: d/dV 1/2 (V-R)^2 / 3 = (0.5 - 1) / 3
    torch.testing.assert_close(values.grad, torch.tensor([[0.0, 0.0, 0.0, -0.5 / 3]]))


def test_value_loss_unclipped_and_properties():
    values, old, returns, mask = _value_case()
    loss, m = losses.value_loss(values, old, returns, mask, clip_range=None)
    assert loss.item() == pytest.approx(0.5 * (1.0 + 0.0 + 0.25) / 3)  # 0.2083333
    assert m["value_clip_frac"] == 0.0
    # perfect values: loss 0, explained variance 1; constant returns: explained variance NaN
    r = torch.tensor([[1.0, 2.0, 3.0]])
    full = torch.ones(1, 3, dtype=torch.bool)
    lp, mp = losses.value_loss(r.clone(), r.clone(), r, full, clip_range=0.2)
    assert lp.item() == 0.0 and mp["explained_variance"] == pytest.approx(1.0)
    assert math.isnan(losses.value_loss(r, r, torch.ones(1, 3), full, clip_range=0.2)[1]["explained_variance"])
    # clipped loss is never below the unclipped one
    g = torch.Generator().manual_seed(0)
    v, o, R = (torch.randn(4, 6, generator=g) for _ in range(3))
    m6 = torch.ones(4, 6, dtype=torch.bool)
    assert losses.value_loss(v, o, R, m6, clip_range=0.1)[0] >= losses.value_loss(v, o, R, m6, clip_range=None)[0]


def test_masked_reductions_come_from_logprobs():
    from posttrain import logprobs

    assert losses.masked_mean is logprobs.masked_mean and losses.masked_sum is logprobs.masked_sum
    assert not any(callable(v) and getattr(v, "__module__", "") == losses.__name__ and k.startswith("_masked")
                   for k, v in vars(losses).items())


# ----------------------------------------------------------------------------- GSPO, CISPO
def _gspo_case():
    """Sequence 1: completion tokens with ratios 1.5, 0.5, 0.5 and A = +1; sequence 2: one token, ratio 0.7,
    A = -2. NaN outside the mask."""
    nan = float("nan")
    mask = torch.tensor([[0, 1, 1, 1], [0, 1, 0, 0]], dtype=torch.bool)
    old = torch.full((2, 4), -1.0)
    ratios = torch.tensor([[1.0, 1.5, 0.5, 0.5], [1.0, 0.7, 1.0, 1.0]])
    logps = old + ratios.log()
    logps[~mask] = nan
    return logps.requires_grad_(True), old, torch.tensor([1.0, -2.0]), mask


def test_gspo_hand_computed_and_gradient():
    logps, old, adv, mask = _gspo_case()
    loss, m = losses.gspo_policy_loss(logps, old, adv, mask, clip_eps=0.2)
    # s_1 = (1.5 * 0.5 * 0.5)^(1/3) = 0.375^(1/3) = 0.7211248; A = +1: max(-0.7211, -0.8) = -0.7211 (unclipped)
    # s_2 = 0.7; A = -2: max(1.4, -2 * 0.8 = 1.6) = 1.6 (clipped, low); mean over the 2 sequences
    s1 = 0.375 ** (1 / 3)
    assert s1 == pytest.approx(0.7211248, abs=1e-7)
    assert loss.item() == pytest.approx((-s1 + 1.6) / 2)  # 0.4394376
    assert m["clip_frac"] == pytest.approx(0.5) and m["clip_frac_low"] == pytest.approx(0.5)
    assert m["clip_frac_high"] == 0.0
    assert m["ratio_mean"] == pytest.approx((s1 + 0.7) / 2) and m["ratio_max"] == pytest.approx(0.7211248, abs=1e-6)
    k3 = sum(r - 1 - math.log(r) for r in (1.5, 0.5, 0.5, 0.7)) / 4  # token-level, over the 4 tokens
    assert m["approx_kl"] == pytest.approx(k3)
    loss.backward()
    # d/d logp_t of -A s_1 / 2 with s_1 = exp(mean_t log r_t): -A s_1 / (2 * 3) on each of the 3 tokens;
    # sequence 2 is clipped: no gradient
    g = -s1 / 6
    torch.testing.assert_close(logps.grad, torch.tensor([[0.0, g, g, g], [0.0, 0.0, 0.0, 0.0]]))


def test_gspo_token_equals_gspo_with_sequence_advantages():
    logps, old, adv, mask = _gspo_case()
    seq, m_seq = losses.gspo_policy_loss(logps, old, adv, mask, clip_eps=0.2)
    (g_seq,) = torch.autograd.grad(seq, logps)
    tok, m_tok = losses.gspo_policy_loss(logps, old, adv, mask, clip_eps=0.2, token_level=True)
    (g_tok,) = torch.autograd.grad(tok, logps)
    assert tok.item() == pytest.approx(seq.item())
    torch.testing.assert_close(g_tok, g_seq)  # GSPO §4.3: the same gradient when A is per sequence
    # per-token advantages are GSPO-token only: the sequence form refuses them
    with pytest.raises(ValueError, match="one advantage per sequence"):
        losses.gspo_policy_loss(logps, old, adv[:, None].expand(2, 4), mask, clip_eps=0.2)
    with pytest.raises(ValueError, match="mean over sequences"):
        losses.gspo_policy_loss(logps, old, adv, mask, clip_eps=0.2, aggregation="token_mean")


def test_gspo_on_policy_and_sequence_weights():
    logps, old, adv, mask = _gspo_case()
    same, m = losses.gspo_policy_loss(old.clone(), old, adv, mask, clip_eps=3e-4, clip_eps_high=4e-4)
    assert same.item() == pytest.approx(-adv.mean().item()) and m["clip_frac"] == 0.0  # ratio 1: -mean(A)
    w = torch.tensor([[9.0, 2.0, 2.0, 2.0], [9.0, 0.5, 9.0, 9.0]])  # constant on each sequence's tokens
    weighted, _ = losses.gspo_policy_loss(logps, old, adv, mask, clip_eps=0.2, weights=w)
    assert weighted.item() == pytest.approx((-2.0 * 0.375 ** (1 / 3) + 0.5 * 1.6) / 2)
    with pytest.raises(ValueError, match="vary"):
        losses.gspo_policy_loss(logps, old, adv, mask, clip_eps=0.2, weights=torch.rand(2, 4) + 1)


def test_cispo_hand_computed_and_gradient_keeps_clipped_tokens():
    logps, old, adv, mask = _ppo_case()  # ratios 1.5, 0.5, 0.5 (A = 1, 1, -2) and 1.1 (A = 3)
    loss, m = losses.cispo_policy_loss(logps, old, adv, mask, clip_eps=0.2)
    # w = clip(r, 0.8, 1.2) = 1.2, 0.8, 0.8, 1.1; values -A w = -1.2, -0.8, 1.6, -3.3; token mean
    assert loss.item() == pytest.approx((-1.2 - 0.8 + 1.6 - 3.3) / 4)  # -0.925
    assert m["clip_frac"] == pytest.approx(0.75)  # 3 of 4 weights capped
    assert m["clip_frac_low"] == pytest.approx(0.5) and m["clip_frac_high"] == pytest.approx(0.25)
    loss.backward()
    # gradient -A w / 4 on every token, the clipped ones included (PPO gives 0 on tokens 1 and 3)
    expected = torch.tensor([[0.0, -1.2 / 4, -0.8 / 4, 2 * 0.8 / 4], [0.0, -3.0 * 1.1 / 4, 0.0, 0.0]])
    torch.testing.assert_close(logps.grad, expected)
    # no lower bound (MiniMax-M1): clip_eps = 1 -> w = 1.2, 0.5, 0.5, 1.1
    free, _ = losses.cispo_policy_loss(logps, old, adv, mask, clip_eps=1.0, clip_eps_high=0.2)
    assert free.item() == pytest.approx((-1.2 - 0.5 + 1.0 - 3.3) / 4)  # -1.0


def test_cispo_on_policy_gradient_equals_ppo():
    g = torch.Generator().manual_seed(4)
    logps = (-torch.rand(3, 5, generator=g)).requires_grad_(True)
    adv = torch.randn(3, 5, generator=g)
    mask = torch.rand(3, 5, generator=g) > 0.3
    for agg in ("token_mean", "seq_mean_token_mean"):
        a, _ = losses.cispo_policy_loss(logps, logps.detach().clone(), adv, mask, clip_eps=0.2, aggregation=agg)
        b, _ = losses.ppo_policy_loss(logps, logps.detach().clone(), adv, mask, clip_eps=0.2, aggregation=agg)
        assert a.item() == pytest.approx(b.item(), abs=1e-6)
        torch.testing.assert_close(torch.autograd.grad(a, logps)[0], torch.autograd.grad(b, logps)[0])


def test_policy_loss_dispatches_by_name():
    logps, old, adv, mask = _gspo_case()
    for kind, fn, kw in (("clip", losses.ppo_policy_loss, {}), ("cispo", losses.cispo_policy_loss, {}),
                         ("gspo_token", losses.gspo_policy_loss, {"token_level": True})):
        a, _ = losses.policy_loss(kind, logps, old, adv, mask, clip_eps=0.2, aggregation="seq_mean_token_mean")
        b, _ = fn(logps, old, adv, mask, clip_eps=0.2, aggregation="seq_mean_token_mean", **kw)
        assert a.item() == pytest.approx(b.item())
    a, _ = losses.policy_loss("gspo", logps, old, adv, mask, clip_eps=0.2, aggregation="seq_mean_token_mean")
    assert a.item() == pytest.approx((-(0.375 ** (1 / 3)) + 1.6) / 2)
    with pytest.raises(ValueError, match="unknown kind"):
        losses.policy_loss("sapo", logps, old, adv, mask, clip_eps=0.2)


def test_ppo_policy_loss_weights_scale_each_token():
    logps, old, adv, mask = _ppo_case()
    w = torch.tensor([[float("nan"), 2.0, 0.5, 1.0], [float("nan"), 3.0, float("nan"), float("nan")]])
    loss, _ = losses.ppo_policy_loss(logps, old, adv, mask, clip_eps=0.2, weights=w)
    # per-token -1.2, -0.5, 1.6, -3.3 (test above) times 2, 0.5, 1, 3
    assert loss.item() == pytest.approx((-2.4 - 0.25 + 1.6 - 9.9) / 4)
    loss.backward()
    expected = torch.tensor([[0.0, 0.0, 0.5 * -0.5 / 4, 0.0], [0.0, 3 * -3.3 / 4, 0.0, 0.0]])
    torch.testing.assert_close(logps.grad, expected)  # finite: the NaN weights sit outside the mask


# ----------------------------------------------------------------------------- rollout correction
def _mismatch_case():
    """Token ratios pi_train / pi_sampler: 3, 0.25, 1.5 on sequence 1 and 0.9 on sequence 2 (one token)."""
    mask = torch.tensor([[1, 1, 1], [1, 0, 0]], dtype=torch.bool)
    sampler = torch.full((2, 3), -2.0)
    train = sampler + torch.tensor([[3.0, 0.25, 1.5], [0.9, 1.0, 1.0]]).log()
    train[~mask] = float("nan")
    return train, sampler, mask


def test_sampler_mismatch_hand_computed():
    train, sampler, mask = _mismatch_case()
    m = losses.sampler_mismatch(train, sampler, mask)
    # k3 = w - 1 - log w: 0.9013877 + 0.6362944 + 0.0945349 + 0.0053605 = 1.6375775, over 4 tokens
    assert m["mismatch/kl"] == pytest.approx(sum(w - 1 - math.log(w) for w in (3, 0.25, 1.5, 0.9)) / 4)
    assert m["mismatch/kl"] == pytest.approx(0.4093944, abs=1e-6)
    assert m["mismatch/max_ratio"] == pytest.approx(3.0) and m["mismatch/min_ratio"] == pytest.approx(0.25)
    same = losses.sampler_mismatch(sampler, sampler.clone(), mask)
    assert same["mismatch/kl"] == 0.0 and same["mismatch/max_ratio"] == 1.0


def test_rollout_correction_hand_computed():
    train, sampler, mask = _mismatch_case()
    w, keep, m = losses.rollout_correction(train, sampler, mask, kind="tis", cap=2.0)
    torch.testing.assert_close(w[mask], torch.tensor([2.0, 0.25, 1.5, 0.9]))  # min(w, 2)
    assert torch.equal(keep, mask)
    assert m["correction/truncated"] == pytest.approx(0.25)
    assert m["correction/weight_mean"] == pytest.approx(4.65 / 4)
    w, keep, m = losses.rollout_correction(train, sampler, mask, kind="mask", cap=2.0)
    # kept: w in [0.5, 2]: 1.5 and 0.9; 3 and 0.25 are dropped from the loss
    assert keep.tolist() == [[False, False, True], [True, False, False]]
    torch.testing.assert_close(w[keep], torch.tensor([1.5, 0.9]))
    assert m["correction/masked"] == pytest.approx(0.5) and m["correction/weight_mean"] == pytest.approx(1.2)
    # sequence level: the geometric mean of each sequence's ratios, (3 * 0.25 * 1.5)^(1/3) = 1.125^(1/3), and 0.9
    g = 1.125 ** (1 / 3)
    w, keep, m = losses.rollout_correction(train, sampler, mask, kind="tis", level="sequence", cap=2.0)
    torch.testing.assert_close(w[mask], torch.tensor([g, g, g, 0.9]))
    assert m["correction/truncated"] == 0.0 and m["correction/weight_mean"] == pytest.approx((3 * g + 0.9) / 4)
    w, keep, m = losses.rollout_correction(train, sampler, mask, kind="mask", level="sequence", cap=1.05)
    assert keep.tolist() == [[True, True, True], [False, False, False]]  # 1.040 inside [1/1.05, 1.05]; 0.9 not
    none_w, none_keep, none_m = losses.rollout_correction(train, sampler, mask, kind="none")
    assert none_w is None and torch.equal(none_keep, mask) and none_m == {}
    with pytest.raises(ValueError, match="cap"):
        losses.rollout_correction(train, sampler, mask, kind="tis", cap=1.0)


def test_rollout_correction_bounds_a_perturbed_sampler():
    """An artificially perturbed sampler (log-probs off by N(0, 1) per token): TIS caps every weight at C,
    masking keeps exactly the tokens with w in [1/C, C], and both bound the gradient of the weighted loss."""
    g = torch.Generator().manual_seed(5)
    B, T, C = 16, 12, 2.0
    train = -3 * torch.rand(B, T, generator=g)
    sampler = train + torch.randn(B, T, generator=g)
    mask = torch.rand(B, T, generator=g) > 0.2
    w_raw = (train - sampler).exp()
    assert w_raw[mask].max() > 3 * C  # the perturbation produces weights far above the cap
    w, keep, m = losses.rollout_correction(train, sampler, mask, kind="tis", cap=C)
    assert w[mask].max() <= C and torch.equal(keep, mask) and m["correction/truncated"] > 0.1
    w_m, keep_m, m_m = losses.rollout_correction(train, sampler, mask, kind="mask", cap=C)
    inside = mask & (w_raw >= 1 / C) & (w_raw <= C)
    assert torch.equal(keep_m, inside) and w_m[keep_m].max() <= C and w_m[keep_m].min() >= 1 / C
    assert m_m["correction/masked"] == pytest.approx(1 - inside.sum().item() / mask.sum().item())
    # the weighted on-policy loss's per-token gradient is bounded by C |A| / n (n = loss tokens)
    adv = torch.randn(B, generator=g)
    logps = train.clone().requires_grad_(True)
    for weights, lm in ((w, keep), (w_m, keep_m)):
        loss, _ = losses.ppo_policy_loss(logps, train, adv, lm, clip_eps=0.2, weights=weights)
        (grad,) = torch.autograd.grad(loss, logps)
        bound = C * adv.abs()[:, None] / lm.sum()
        assert bool((grad.abs() <= bound + 1e-7).all())
    # no perturbation: weights 1, nothing dropped, no mismatch
    w0, keep0, m0 = losses.rollout_correction(train, train.clone(), mask, kind="mask", cap=C)
    assert torch.equal(keep0, mask) and m0["correction/masked"] == 0.0 and float(w0[mask].max()) == 1.0
    assert losses.sampler_mismatch(train, train.clone(), mask)["mismatch/kl"] == 0.0


def test_untruncated_importance_weights_correct_the_expectation_exactly():
    # E_sampler[w f] = E_train[f] on an enumerable distribution: the weights are the right ones
    p = torch.tensor([0.5, 0.3, 0.15, 0.05])  # trainer
    q = torch.tensor([0.25, 0.25, 0.25, 0.25])  # sampler
    f = torch.tensor([1.0, -2.0, 4.0, 3.0])
    w, _, _ = losses.rollout_correction(p.log()[None], q.log()[None], torch.ones(1, 4, dtype=torch.bool),
                                        kind="tis", cap=1e9)
    assert float((q * w[0] * f).sum()) == pytest.approx(float((p * f).sum()))
    capped, _, _ = losses.rollout_correction(p.log()[None], q.log()[None], torch.ones(1, 4, dtype=torch.bool),
                                             kind="tis", cap=1.5)
    assert float(capped.max()) == 1.5  # truncation trades this exactness for bounded variance


# ----------------------------------------------------------------------------- KTO
def test_kto_hand_computed_and_gradient():
    # r = policy - reference = [1, -1, 0]; z0 = mean([-4 - -5, -6 - -6]) = 0.5; beta 0.5, w_D 1, w_U 2:
    # rows 1 - s(0.25), 2 (1 - s(0.75)), 1 - s(-0.25); the first and last sum to 1
    pol = torch.tensor([-2.0, -5.0, -3.0], requires_grad=True)
    ref = torch.tensor([-3.0, -4.0, -3.0])
    des = torch.tensor([True, False, True])
    kl_pol = torch.tensor([-4.0, -6.0], requires_grad=True)
    loss, m = losses.kto_loss(pol, ref, des, kl_pol, torch.tensor([-5.0, -6.0]), beta=0.5, desirable_weight=1.0,
                              undesirable_weight=2.0)
    assert loss.item() == pytest.approx((1 + 2 * (1 - _sig(0.75))) / 3)
    assert loss.item() == pytest.approx(0.5472140, abs=1e-6)
    assert m["kl"] == pytest.approx(0.5) and m["rewards/chosen"] == pytest.approx(0.25)
    assert m["rewards/rejected"] == pytest.approx(-0.5) and m["rewards/margin"] == pytest.approx(0.75)
    assert m["rewards/accuracy"] == pytest.approx(2 / 3)
    assert m["logps/chosen"] == pytest.approx(-2.5) and m["logps/rejected"] == pytest.approx(-5.0)
    loss.backward()

    def ds(x):  # sigmoid'(x)
        return _sig(x) * (1 - _sig(x))
    torch.testing.assert_close(pol.grad, torch.tensor([-0.5 * ds(0.25) / 3, 2 * 0.5 * ds(0.75) / 3,
                                                       -0.5 * ds(-0.25) / 3]))
    assert kl_pol.grad is None  # the reference point is a constant (detached)


def test_kto_reference_point_is_clamped_at_zero_and_one_class_batches():
    pol, ref = torch.tensor([-1.0, -2.0]), torch.tensor([-1.0, -2.0])
    # the mismatched completions are likelier under the reference: the KL estimate is negative, z0 = 0
    loss, m = losses.kto_loss(pol, ref, torch.tensor([True, True]), torch.tensor([-9.0]), torch.tensor([-3.0]),
                              beta=0.1)
    assert m["kl"] == 0.0 and loss.item() == pytest.approx(0.5)  # r = z0 = 0: 1 - sigmoid(0)
    assert math.isnan(m["rewards/rejected"]) and m["rewards/chosen"] == 0.0
    with pytest.raises(ValueError, match="beta"):
        losses.kto_loss(pol, ref, torch.tensor([True, False]), pol, ref, beta=0.0)


# ----------------------------------------------------------------------------- distillation
def test_token_divergence_hand_computed():
    # vocabulary of 2: student logits (0, 0) -> S = (1/2, 1/2); teacher (log 3, 0) -> P = (3/4, 1/4)
    s = torch.tensor([[[0.0, 0.0]]])
    t = torch.tensor([[[math.log(3.0), 0.0]]])
    mask = torch.ones(1, 1)
    rev = losses.token_divergence(s, t, mask, kind="reverse_kl")
    assert rev.item() == pytest.approx(0.5 * math.log(4 / 3))  # 0.5 ln(0.5/0.75) + 0.5 ln(0.5/0.25)
    fwd = losses.token_divergence(s, t, mask, kind="forward_kl")
    assert fwd.item() == pytest.approx(0.75 * math.log(1.5) - 0.25 * math.log(2))
    # beta 1/2: M = (5/8, 3/8); KL(P||M) = 0.75 ln 1.2 + 0.25 ln(2/3), KL(S||M) = 0.5 ln 0.8 + 0.5 ln(4/3)
    jsd = losses.token_divergence(s, t, mask, kind="jsd", beta=0.5)
    want = 0.5 * (0.75 * math.log(1.2) + 0.25 * math.log(2 / 3)) + 0.5 * (0.5 * math.log(0.8) + 0.5 * math.log(4 / 3))
    assert jsd.item() == pytest.approx(want) and jsd.item() == pytest.approx(0.0338217, abs=1e-6)
    # GKD's limits: JSD(beta) / beta -> forward KL as beta -> 0, JSD / (1 - beta) -> reverse KL as beta -> 1
    eps = 1e-4
    assert losses.token_divergence(s, t, mask, kind="jsd", beta=eps).item() / eps == pytest.approx(fwd.item(), rel=1e-3)
    assert losses.token_divergence(s, t, mask, kind="jsd", beta=1 - eps).item() / eps == \
        pytest.approx(rev.item(), rel=1e-3)


def test_logprob_divergence_from_shared_log_softmaxes_equals_token_divergence():
    """A caller (distillation) computes one log_softmax per side and derives its loss and both KL metrics from them:
    the same values as token_divergence on the logits, garbage outside the mask kept away."""
    g = torch.Generator().manual_seed(0)
    s, t = torch.randn(2, 3, 7, generator=g), torch.randn(2, 3, 7, generator=g)
    mask = torch.tensor([[1, 1, 0], [1, 0, 0]])
    s[0, 2], t[1, 1] = float("nan"), float("inf")
    ls, lp = losses.masked_log_softmax(s, mask), losses.masked_log_softmax(t, mask)
    assert torch.isfinite(ls).all() and torch.isfinite(lp).all()
    for kind in ("reverse_kl", "forward_kl", "jsd"):
        torch.testing.assert_close(losses.logprob_divergence(ls, lp, mask, kind=kind, beta=0.3),
                                   losses.token_divergence(s, t, mask, kind=kind, beta=0.3), atol=0, rtol=0)
    with pytest.raises(ValueError, match="jsd needs 0 < beta < 1"):
        losses.logprob_divergence(ls, lp, mask, kind="jsd", beta=1.0)


def test_token_divergence_gradients_by_hand_and_masking():
    s = torch.tensor([[[0.0, 0.0], [float("nan"), 1.0]]], requires_grad=True)  # the second position is masked
    t = torch.tensor([[[math.log(3.0), 0.0], [0.0, float("inf")]]])
    mask = torch.tensor([[1.0, 0.0]])
    rev = losses.token_divergence(s, t, mask, kind="reverse_kl")
    assert rev[0, 1].item() == 0.0 and torch.isfinite(rev).all()
    rev.sum().backward()
    # d KL(S||P) / d z_i = S_i (log S_i - log P_i - KL)
    kl = 0.5 * math.log(4 / 3)
    torch.testing.assert_close(s.grad[0, 0], torch.tensor([0.5 * (math.log(2 / 3) - kl), 0.5 * (math.log(2) - kl)]))
    assert s.grad[0, 1].eq(0).all()  # nothing reaches a masked position, NaN included
    s.grad = None
    losses.token_divergence(s, t, mask, kind="forward_kl").sum().backward()
    torch.testing.assert_close(s.grad[0, 0], torch.tensor([0.5 - 0.75, 0.5 - 0.25]))  # d KL(P||S) / d z = S - P


def test_token_divergence_is_zero_for_equal_distributions_and_checks_its_inputs():
    g = torch.Generator().manual_seed(0)
    z = torch.randn(2, 3, 7, generator=g)
    mask = torch.ones(2, 3)
    for kind in ("reverse_kl", "forward_kl", "jsd"):
        assert losses.token_divergence(z, z + 5.0, mask, kind=kind).abs().max().item() < 1e-6  # a shift is no change
        d = losses.token_divergence(z, torch.randn(2, 3, 7, generator=g), mask, kind=kind)
        assert (d > 0).all()
    with pytest.raises(ValueError, match="beta"):
        losses.token_divergence(z, z, mask, kind="jsd", beta=1.0)
    with pytest.raises(ValueError, match="kind"):
        losses.token_divergence(z, z, mask, kind="tv")
    with pytest.raises(ValueError, match="agree"):
        losses.token_divergence(z, z[..., :5], mask)
