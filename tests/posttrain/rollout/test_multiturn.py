"""Multi-turn episodes (posttrain.rollout.multiturn): one exact token sequence per episode, the trainer's log-probs
equal to the sampling ones, per-row determinism, tools that hang or fail, templates that rewrite earlier turns.

The model is a random tiny Llama with a chat tokenizer whose eos row of the output matrix is pointed along the mean
final hidden state, so turns end at eos after a few tokens (a random model otherwise rarely samples it). The
environment answers every turn with a tool result until its turn limit, so episodes have several turns without a
trained model."""
import random
import time

import pytest
import torch

from posttrain.chat import encode_prompts, render_prompt
from posttrain.errors import ModelError
from posttrain.logprobs import batched_logprobs
from posttrain.rollout import collate_rollouts
from posttrain.rollout.multiturn import episode_metrics, generate_episodes
from posttrain.verifiers.envs import Environment, Limits, ToolCall


@pytest.fixture(scope="module")
def chat_lm():
    from posttrain.models import build_model, train_tokenizer

    rng = random.Random(0)
    corpus = [f"what is {rng.randint(0, 99)} + {rng.randint(0, 99)} ? the answer is {rng.randint(0, 200)}"
              for _ in range(300)]
    tok = train_tokenizer(corpus, vocab_size=300, chat=True)
    model = build_model("tiny", tok, seed=0).eval()
    with torch.no_grad():
        enc = tok(corpus[:20], return_tensors="pt", padding=True)
        h = model.model(**enc).last_hidden_state[enc["attention_mask"].bool()].mean(0)
        model.lm_head.weight[tok.eos_token_id] = 1.0 * h / h.norm()
    return model, tok


def add(a: int, b: int) -> str:
    """Add two integers.

    Args:
        a: the first number
        b: the second number
    """
    return str(a + b)


class Echo(Environment):
    """Every turn calls `add` with the turn's length (so a random model's episode has several turns)."""

    name = "echo"
    tools = (add,)

    def __init__(self, turns: int = 3, sleep=None, **limits):
        self.limits = Limits(**{"max_turns": turns, "max_turn_tokens": 40, "max_total_tokens": 200, **limits})
        self.sleep = sleep

    def parse_calls(self, text, episode=None):
        return [ToolCall("add", {"a": len(text), "b": 1}, text)]

    def respond(self, episode, results):
        if self.sleep is not None:
            self.sleep(episode)
        return super().respond(episode, results)

    def reward(self, episode):
        return float(len(episode.turns))


PROBLEMS = [{"prompt": f"what is {i} + {i + 1} ?"} for i in range(6)]


def segments(r):
    """(mask, tokens) runs of a rollout's completion."""
    out = []
    for t, m in zip(r.completion_ids, r.completion_mask):
        if out and out[-1][0] == m:
            out[-1][1].append(t)
        else:
            out.append((m, [t]))
    return out


def test_a_trajectory_is_the_sampled_tokens_and_the_templates_exact_suffixes(chat_lm):
    model, tok = chat_lm
    rs = generate_episodes(model, tok, Echo(), PROBLEMS, n=2, seed=1)
    assert len(rs) == 12 and [(r.prompt_index, r.sample_index) for r in rs] == [(i, j) for i in range(6) for j in (0, 1)]
    multi = 0
    for r in rs:
        ep = r.extras["episode"]
        first = Echo().reset(PROBLEMS[r.prompt_index])
        assert r.prompt_ids == encode_prompts(tok, [first])[0]
        segs = segments(r)
        sampled = [s for m, s in segs if m == 1]
        env = [s for m, s in segs if m == 0]
        assert len(sampled) == len(ep["turns"]) and len(env) == sum(t["env_tokens"] > 0 for t in ep["turns"])
        # every environment segment is exactly what the template adds after the previous rendering + eos
        messages = list(first)
        rendered = render_prompt(tok, messages)
        for k, t in enumerate(ep["turns"][:len(env)]):
            assert sampled[k][-1] == tok.eos_token_id  # the turn ended at eos (the sampled eos is kept, mask 1)
            assert tok.decode(sampled[k][:-1], skip_special_tokens=True) == t["text"]
            messages = messages + [{"role": "assistant", "content": t["text"]}] + \
                [{"role": "tool", "content": c["content"]} for c in t["tool_calls"]]
            after = render_prompt(tok, messages)
            before = rendered + t["text"] + tok.eos_token
            assert after.startswith(before)
            assert env[k] == tok(after[len(before):], add_special_tokens=False)["input_ids"]
            assert t["tool_calls"][0]["content"] == str(len(t["text"]) + 1)
            rendered = after
        multi += len(ep["turns"]) > 1
        assert r.logprobs[-1] != 0 or r.completion_mask[-1] == 1
        assert all(lp == 0.0 for lp, m in zip(r.policy_logprobs, r.completion_mask) if m == 0)
        assert r.reward == float(len(ep["turns"]))
    assert multi >= 3  # several episodes have several turns (10 of 12 here: room for another CPU's rounding)
    m = episode_metrics(rs)
    assert m["env/turns"] > 1.2 and m["env/valid_calls"] == m["env/tool_calls"] > 0
    assert m["env/env_tokens"] > 0 and m["env/sampled_tokens"] > 0


@pytest.mark.parametrize("backend", ["lean", "hf"])
def test_the_trainers_log_probs_equal_the_sampling_ones_on_multi_turn_trajectories(chat_lm, backend):
    model, tok = chat_lm
    rs = generate_episodes(model, tok, Echo(), PROBLEMS, n=2, seed=2, backend=backend)
    batch = collate_rollouts(rs, tok.pad_token_id)
    lp, _ = batched_logprobs(model, batch)
    sampled = batch.completion_mask.bool()
    assert int((batch.completion_mask == 0).logical_and(batch.attention_mask.bool()).sum()) > 0  # env tokens exist
    diff = (lp[sampled] - batch.policy_logprobs[sampled])
    assert float(diff.abs().max()) < 1e-4
    assert abs(float(diff.mean())) < 1e-5  # the mismatch KL estimate (k1) is ~0
    assert float(lp[~sampled & batch.attention_mask.bool()].abs().sum()) == 0.0  # env tokens carry no loss


def test_a_rows_episode_does_not_depend_on_its_neighbours_or_on_tool_time(chat_lm):
    model, tok = chat_lm
    base = generate_episodes(model, tok, Echo(), PROBLEMS, n=2, seed=3)
    rng = random.Random(0)
    slow = Echo(sleep=lambda ep: time.sleep(rng.random() * 0.05))
    order = [4, 1, 3]
    again = generate_episodes(model, tok, slow, [PROBLEMS[i] for i in order], n=2, seed=3, prompt_keys=order)
    for r in again:
        ref = base[2 * order[r.prompt_index] + r.sample_index]
        assert r.completion_ids == ref.completion_ids and r.completion_mask == ref.completion_mask
        assert r.logprobs == pytest.approx(ref.logprobs, abs=1e-4)


def sleepy(seconds: float) -> str:
    """Sleep, then say so.

    Args:
        seconds: how long to sleep
    """
    time.sleep(seconds)
    return "awake"


class Sleepy(Environment):
    """The calls of a problem whose prompt starts with HANG sleep 60 s (the limit is 0.5 s); the others' return."""

    name = "sleepy"
    tools = (sleepy,)
    limits = Limits(max_turns=2, max_turn_tokens=40, max_total_tokens=160, tool_timeout_s=0.5)

    def parse_calls(self, text, episode=None):
        return [ToolCall("sleepy", {"seconds": 60.0 if episode.problem["prompt"].startswith("HANG") else 0.0}, text)]

    def reward(self, episode):
        return 0.0


def test_a_hung_tool_times_out_and_does_not_stall_the_batch(chat_lm):
    model, tok = chat_lm
    problems = [{"prompt": "HANG what is 1 + 2 ?"}] + PROBLEMS[:3]
    t = time.monotonic()
    rs = generate_episodes(model, tok, Sleepy(), problems, n=2, seed=4)
    assert time.monotonic() - t < 20  # 60 s tools under a 0.5 s limit: the batch went on
    hung = [c for r in rs[:2] for tt in r.extras["episode"]["turns"] for c in tt["tool_calls"]]
    fine = [c for r in rs[2:] for tt in r.extras["episode"]["turns"] for c in tt["tool_calls"]]
    assert hung and all(c["error"] == "timeout" and c["content"] == "error: timeout after 0.5 s" for c in hung)
    assert fine and all(c["error"] is None and c["content"] == "awake" for c in fine)
    assert episode_metrics(rs)["env/errors/timeout"] > 0


def test_a_template_that_rewrites_earlier_turns_is_refused(chat_lm):
    model, tok = chat_lm
    import copy

    odd = copy.deepcopy(tok)
    # drops every assistant turn but the last (as templates that strip past reasoning do)
    odd.chat_template = (
        "{%- for message in messages -%}"
        "{%- if message['role'] != 'assistant' or loop.last %}{{ '<|' + message['role'] + '|>' + message['content'] }}"
        "{%- if message['role'] == 'assistant' %}{{ eos_token }}{% endif %}{% endif -%}"
        "{%- endfor -%}"
        "{%- if add_generation_prompt %}{{ '<|assistant|>' }}{% endif -%}")
    with pytest.raises(ModelError, match="does not render a conversation as a prefix of its continuation"):
        generate_episodes(model, odd, Echo(turns=3), PROBLEMS[:2], n=2, seed=1)


def test_bad_arguments_and_limits_are_one_line_errors(chat_lm):
    model, tok = chat_lm
    with pytest.raises(ValueError, match="stop strings and ignore_eos do not apply"):
        generate_episodes(model, tok, Echo(), PROBLEMS[:1], stop=["x"])
    with pytest.raises(ValueError, match="prompt_keys has 1 entries for 2 problems"):
        generate_episodes(model, tok, Echo(), PROBLEMS[:2], prompt_keys=[0])
    with pytest.raises(ValueError, match="Limits.max_turns must be a positive integer"):
        Limits(max_turns=0)


class Counted(Echo):
    """Echo whose `metrics` reports the episode's turns and calls (`bad` returns what an environment must not)."""

    name = "counted"

    def __init__(self, bad=None, **kw):
        super().__init__(**kw)
        self.bad = bad

    def metrics(self, episode):
        if self.bad is not None:
            return self.bad
        return {"turns_seen": len(episode.turns), "calls_seen": sum(len(t.results) for t in episode.turns)}


def test_the_environments_own_metrics_are_saved_with_each_episode_and_averaged(chat_lm):
    model, tok = chat_lm
    rs = generate_episodes(model, tok, Counted(), PROBLEMS[:3], n=2, seed=3)
    for r in rs:
        ep = r.extras["episode"]
        assert ep["metrics"] == {"turns_seen": float(len(ep["turns"])),
                                 "calls_seen": float(sum(len(t["tool_calls"]) for t in ep["turns"]))}
    m = episode_metrics(rs)
    assert m["env/turns_seen"] == pytest.approx(m["env/turns"]) and m["env/calls_seen"] == pytest.approx(
        m["env/tool_calls"])


@pytest.mark.parametrize("bad", [(), {"x": float("nan")}, {"x": "high"}, [1.0]])
def test_an_environments_bad_metrics_are_one_line_errors_naming_it(chat_lm, bad):
    model, tok = chat_lm
    env = Counted(bad=bad)
    with pytest.raises(ValueError, match="environment 'counted': metrics\\(episode\\) must return a dict"):
        generate_episodes(model, tok, env, PROBLEMS[:1], n=1, seed=0)
