"""The scoring interface: reward model (batched, left-pad aware), verifiers under hard timeouts, gold, weighted sums."""
import time

import pytest
import torch

from posttrain.scoring import (GoldScorer, RewardModelScorer, ScoreResult, VerifierScorer, WeightedScorer,
                               left_pad, reward_forward)
from posttrain.tasks import summarize
from posttrain.verifiers.base import Verdict, Verifier
from posttrain.verifiers.runner import VerifierPool


class Hangs(Verifier):
    """1.0 for anything, but never returns on the completion "hang"."""

    name = "hangs"
    timeout_s = 30.0

    def check(self, completion, reference):
        if completion == "hang":
            time.sleep(60)  # far past the limit; the runner kills the worker
        return Verdict(1.0, "ok")


class HasWord(Verifier):
    """1.0 when the reference word is in the completion."""

    name = "has_word"
    in_process = True

    def check(self, completion, reference):
        ok = str(reference) in completion
        return Verdict(1.0 if ok else 0.0, "found" if ok else f"no {reference!r}")


class Constant:
    def __init__(self, name, value):
        self.name, self.value = name, value

    def score(self, prompts, completions, references=None):
        return ScoreResult([self.value] * len(completions), {"c": [self.value] * len(completions)},
                           [f"{self.name} says hi"] * len(completions))


@pytest.fixture(scope="module")
def tiny_rm(tmp_path_factory, tiny_lm):
    """A randomly initialised one-label sequence-classification model with our tokenizer, saved as a HF dir."""
    from transformers import AutoModelForSequenceClassification

    from posttrain.models import load_tokenizer

    root = tmp_path_factory.mktemp("rm")
    lm = tiny_lm("tiny-summarize", max_length=160)
    tok = load_tokenizer(lm)
    torch.manual_seed(0)
    rm = AutoModelForSequenceClassification.from_pretrained(str(lm), num_labels=1)
    rm.config.pad_token_id = tok.pad_token_id
    with torch.no_grad():
        rm.score.weight.normal_(0, 1.0)  # make rewards clearly differ between inputs
    rm.save_pretrained(root / "rm")
    tok.save_pretrained(root / "rm")
    return root / "rm"


def test_reward_model_scorer_is_batch_invariant_and_matches_hf_pooling(tiny_rm):
    rows = summarize.make_examples(6, 0, "eval")
    prompts = [r["prompt"] for r in rows]
    comps = [r["completion"] for r in rows]
    scorer = RewardModelScorer(tiny_rm, batch_size=4)
    together = scorer.score(prompts, comps).rewards
    alone = [scorer.score([p], [c]).rewards[0] for p, c in zip(prompts, comps)]
    assert together == pytest.approx(alone, abs=1e-4)
    assert len(set(round(x, 4) for x in together)) > 1  # not a constant
    # HF's own pooling (rightmost non-pad token) on a left-padded batch agrees with reward_forward
    from posttrain.scoring import rm_token_ids

    ids, am = left_pad(rm_token_ids(scorer.tokenizer, prompts, comps), scorer.tokenizer.pad_token_id)
    with torch.no_grad():
        ours = reward_forward(scorer.model, ids, am)
        from posttrain.logprobs import position_ids_from_mask

        hf = scorer.model(input_ids=ids, attention_mask=am, position_ids=position_ids_from_mask(am)).logits[:, 0]
    assert torch.allclose(ours, hf, atol=1e-5)
    assert list(ours) == pytest.approx(together, abs=1e-4)
    assert scorer.score(prompts, comps).parts == {"rm": pytest.approx(together, abs=1e-6)}


def test_reward_forward_refuses_right_padding(tiny_rm):
    scorer = RewardModelScorer(tiny_rm)
    ids = torch.tensor([[5, 6, 7], [5, 6, 0]])
    with pytest.raises(ValueError, match="LEFT-padded"):
        reward_forward(scorer.model, ids, (ids != 0).long())


def test_verifier_scorer_hanging_verifier_scores_zero_timeout_and_returns():
    with VerifierPool(workers=1, timeout_s=1.0) as pool:
        scorer = VerifierScorer(Hangs(), pool)
        t0 = time.time()
        res = scorer.score(["p"] * 3, ["a", "hang", "b"], [None] * 3)
        assert time.time() - t0 < 20
    assert res.rewards == [1.0, 0.0, 1.0]
    assert res.reasons == ["ok", "timeout", "ok"]
    assert res.parts == {"hangs": [1.0, 0.0, 1.0]}


def test_verifier_scorer_weighted_mapping_has_parts_and_reasons():
    scorer = VerifierScorer({HasWord(): 3.0, "length": 1.0}, workers=0)
    try:
        res = scorer.score(["p", "p"], ["the cat sat", "a dog"], ["cat", "cat"])
    finally:
        scorer.close()
    assert set(res.parts) == {"has_word", "length"}
    assert res.parts["has_word"] == [1.0, 0.0]
    assert res.rewards[0] > res.rewards[1]
    assert "no 'cat'" in res.reasons[1]


def test_gold_scorer_orders_like_the_gold_preference():
    rows = summarize.make_examples(30, 1, "eval")
    metas = [r["meta"] for r in rows]
    concise = [m["concise_summary"] for m in metas]
    refs = [r["completion"] for r in rows]
    scorer = GoldScorer("tiny-summarize")
    a = scorer.score([r["prompt"] for r in rows], concise, metas)
    assert a.rewards == pytest.approx([1.0] * 30)  # in band, every fact, nothing invented
    b = scorer.score([r["prompt"] for r in rows], refs, metas)
    for m, x, y, rx, ry in zip(metas, concise, refs, a.rewards, b.rewards):
        pref = summarize.gold_prefer(m, x, y)
        assert (rx > ry) == (pref > 0) and (rx == ry) == (pref == 0)
    long = [r for r, d in zip(b.reasons, b.parts["distance"]) if d > 0]
    assert long and all("band" in r for r in long)
    with pytest.raises(ValueError, match="references"):
        scorer.score(["p"], ["s"])


def test_weighted_scorer_sums_parts_and_routes_references():
    s = WeightedScorer([(Constant("a", 1.0), 0.5), (Constant("b", -2.0), 2.0)])
    res = s.score(["p", "q"], ["x", "y"])
    assert res.rewards == [0.5 * 1.0 + 2.0 * -2.0] * 2
    assert res.parts["a"] == [1.0, 1.0] and res.parts["b"] == [-2.0, -2.0] and res.parts["a/c"] == [1.0, 1.0]
    assert res.reasons[0] == "a: a says hi; b: b says hi"
    rows = summarize.make_examples(2, 0, "eval")
    gold_and_word = WeightedScorer([(GoldScorer("tiny-summarize"), 1.0),
                                    (VerifierScorer(HasWord(), workers=0), 0.5)])
    comps = [r["meta"]["concise_summary"] for r in rows]
    out = gold_and_word.score([r["prompt"] for r in rows], comps,
                              {"gold": [r["meta"] for r in rows], "has_word": ["the", "zzz"]})
    assert out.rewards == pytest.approx([1.5, 1.0])
    with pytest.raises(ValueError, match="names must differ"):
        WeightedScorer([(Constant("a", 1), 1), (Constant("a", 2), 1)])
