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
