"""Multi-turn episodes with tools, sampled by the rollout engine's forwards: one token sequence per episode.

    from posttrain.rollout.multiturn import generate_episodes
    from posttrain.verifiers.envs import get_env
    env = get_env("calc")
    rollouts = generate_episodes(model, tokenizer, env, problems, n=4, temperature=1.0, seed=step)
    # r.completion_ids: turn 1's sampled tokens, the environment's tokens, turn 2's sampled tokens, ...
    # r.completion_mask: 1 on sampled tokens, 0 on environment tokens; r.reward = env.reward(episode)

A trajectory is the prompt (the environment's first messages, rendered by the chat template) followed by every
sampled token and every environment token, in order. What that guarantees:
- Sampled tokens are never re-tokenized: the trainer sees exactly the ids that were sampled, and the environment's
  messages are appended as exactly the tokens the chat template adds for them. After an assistant turn the
  conversation, with the assistant's text and the environment's messages, is rendered again; the rendering of what
  came before (the last rendering plus the turn's text plus the eos token's text) must be its prefix, and only the
  rest is tokenized (`add_special_tokens=False`) and appended. A template that rewrites earlier turns (drops past
  reasoning, or closes an assistant turn with something other than the eos token) fails that check, and the
  episode is refused with one ModelError line: this engine does not start new segments.
- Each row keeps its KV cache across turns: only the environment's new tokens are fed. They are fed one per
  decoding step, in the same batched step in which the other rows sample (teacher forcing; a separate chunked
  prefill of them is not implemented), so an environment token costs what a sampled one does.
- A row whose turn ended with tool calls waits for them while the others decode: its calls run in the
  `ToolRunner`'s threads, concurrently with every other row's; the waiting row's cache column of each step is
  masked out (its position does not advance), so its sequence is the same as without the wait. Pause columns are
  bounded (`PAUSE_SLACK`); past that the batch waits for the tools instead of stepping. When no row can step, the
  loop blocks on the tools.
- `completion_mask` is 1 on sampled tokens and 0 on environment tokens; sampling log-probs (and raw policy
  log-probs) are recorded for every sampled token, 0 on environment tokens.
- Determinism per row: a sampled token's uniform is hash(seed, prompt key, sample index, k) where k counts that
  row's sampled tokens, so a row's samples do not depend on its neighbours or on how long tools took (up to the
  floating-point differences between batch layouts that the engine's contract allows).

An episode ends when a turn makes no tool call ("answer"), after `limits.max_turns` turns ("max_turns"), when a
turn reaches `limits.max_turn_tokens` without its eos ("length"), when the next tokens would pass
`limits.max_total_tokens` ("max_tokens"), or when the environment appends nothing ("env"). The Rollout's
`finish_reason` is "eos" when the last sampled token is the eos, else "length". `extras["episode"]` holds the turns
(text, tool calls and results, per-turn rewards, token counts) and the final messages.

Backends: the lean decoder or the HF forward of `select_backend`, eager steps with the key mask (not the static
CUDA-graph step, not vLLM).
"""
from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Sequence

import torch

from ..chat import encode_prompts, render_prompt
from ..errors import ModelError
from ..models import unwrap_model
from .backends import HFForward
from .engine import (DEFAULT_MAX_BATCH_TOKENS, _eos_ids, default_backend, plan_micro_batches, prefill_inputs,
                     select_backend)
from .records import Rollout
from .sampling import Sampler, SamplingParams, row_uniforms

if TYPE_CHECKING:
    from posttrain.verifiers.envs import Environment

PAUSE_SLACK = 0.5  # cache columns for waiting rows, as a fraction of limits.max_total_tokens


def generate_episodes(model, tokenizer, env: Environment, problems: Sequence[dict], sampling: SamplingParams | None = None, *,
                      prompt_keys: Sequence[int] | None = None, runner=None,
                      max_batch_tokens: int = DEFAULT_MAX_BATCH_TOKENS, backend: str | None = None,
                      **overrides) -> list[Rollout]:
    """`n` episodes of `env` for each problem row; Rollouts ordered by (problem, sample), each with its reward
    (`env.reward`) and `extras["episode"]`. `sampling` / `overrides` as in `generate` (`max_new_tokens`, stop
    strings and `ignore_eos` do not apply: the environment's `limits` do). `runner`: a ToolRunner to reuse (one is
    made and closed otherwise)."""
    from posttrain.verifiers.envs import ToolRunner

    params = dataclasses.replace(sampling or SamplingParams(), **overrides).validate()
    if params.stop or params.ignore_eos:
        raise ValueError("generate_episodes: stop strings and ignore_eos do not apply (turns end at the eos token)")
    if getattr(tokenizer, "chat_template", None) is None:
        raise ModelError(f"multi-turn episodes need a chat template; the tokenizer in "
                         f"{getattr(tokenizer, 'name_or_path', '?')!r} has none (set model.chat_template=on)")
    problems = list(problems)
    if not problems:
        return []
    keys = list(range(len(problems))) if prompt_keys is None else [int(k) for k in prompt_keys]
    if len(keys) != len(problems):
        raise ValueError(f"generate_episodes: prompt_keys has {len(keys)} entries for {len(problems)} problems")
    first = [env.reset(p) for p in problems]
    ids = encode_prompts(tokenizer, first)
    limits = env.limits
    backend = default_backend() if backend in (None, "vllm") else backend
    steps = limits.max_total_tokens + int(PAUSE_SLACK * limits.max_total_tokens)
    fwd, _ = select_backend(model, max(len(p) for p in ids) + steps, backend)
    inner = unwrap_model(model)
    vocab = int(inner.get_output_embeddings().weight.shape[0])
    eos = set(_eos_ids(model, tokenizer))
    if not eos:
        raise ModelError("multi-turn episodes need an eos token (the end of an assistant turn)")
    pad = tokenizer.pad_token_id if tokenizer.pad_token_id is not None else 0
    own_runner = runner is None
    runner = runner or ToolRunner()
    out: dict[tuple[int, int], Rollout] = {}
    was_training = getattr(model, "training", False)
    if isinstance(fwd, HFForward) and was_training:
        model.eval()
    try:
        with torch.inference_mode():
            for rows in plan_micro_batches([len(p) for p in ids], params.n, steps, max_batch_tokens):
                batch = _Batch(fwd, env, tokenizer, runner, params, rows, ids, first, problems, keys, eos, pad,
                               vocab, steps)
                out.update(batch.run())
    finally:
        fwd.release()
        if isinstance(fwd, HFForward) and was_training:
            model.train()
        if own_runner:
            runner.close()
    return [out[k] for k in sorted(out)]


def _hide(fwd, rows: list[int], col: int) -> None:
    """Mask cache column `col` of `rows` for every later step (a waiting or finished row's placeholder)."""
    idx = torch.tensor(rows, dtype=torch.long, device=fwd.device)
    if isinstance(fwd, HFForward):
        fwd.mask[idx, col] = 0
    else:  # LeanLlama: additive key mask (rows, kv heads, 1, cols)
        fwd.key_bias[idx, :, :, col] = float("-inf")


class _Batch:
    """One micro-batch of episodes: the per-row state machine sample -> (wait -> force ->) sample ... -> done."""

    def __init__(self, fwd, env: Environment, tokenizer, runner, params, rows, ids, first, problems, keys, eos, pad, vocab, steps):
        from posttrain.verifiers.envs import Episode

        self.fwd, self.env, self.tok, self.runner, self.params = fwd, env, tokenizer, runner, params
        self.rows, self.ids, self.eos, self.pad, self.steps = rows, ids, eos, pad, steps
        self.first = first
        self.limits, self.tools = env.limits, env.tool_functions()
        self.sampler = Sampler(params, vocab)
        self.eos_text = tokenizer.convert_ids_to_tokens(sorted(eos)[0]) if tokenizer.eos_token is None \
            else tokenizer.eos_token
        B = len(rows)
        self.B = B
        self.mode = ["sample"] * B
        self.queue: list[list[int]] = [[] for _ in range(B)]
        self.toks: list[list[int]] = [[] for _ in range(B)]  # completion ids (sampled and environment)
        self.mask: list[list[int]] = [[] for _ in range(B)]
        self.lps: list[list[float]] = [[] for _ in range(B)]
        self.pols: list[list[float]] = [[] for _ in range(B)]
        self.turn: list[list[int]] = [[] for _ in range(B)]  # sampled ids of the current turn
        self.pending: list = [None] * B
        self.episodes = [Episode(problem=problems[i], messages=[dict(m) for m in first[i]]) for i, _ in rows]
        self.rendered = [render_prompt(tokenizer, first[i]) for i, _ in rows]  # text of everything so far
        self.pos = [len(ids[i]) for i, _ in rows]
        self.n_sampled = [0] * B
        self.env_tokens = [0] * B
        self.max_sampled = min(self.limits.max_total_tokens, self.limits.max_turns * self.limits.max_turn_tokens)
        self.u = row_uniforms(params.seed, torch.tensor([keys[i] for i, _ in rows], device=fwd.device),
                              torch.tensor([j for _, j in rows], device=fwd.device), self.max_sampled)  # (B, S)

    # ------------------------------------------------------------------ the loop
    def run(self) -> dict[tuple[int, int], Rollout]:
        fwd, B = self.fwd, self.B
        dev = fwd.device
        prompts, ids_t, valid, pos, row_of = prefill_inputs(self.rows, self.ids, self.pad, dev)
        Tp = ids_t.shape[1]
        fwd.start(B, Tp + self.steps, max(len(self.ids[i]) for i in prompts) + self.limits.max_total_tokens + 1)
        logits = fwd.prefill(ids_t, valid, pos, row_of)
        cols = Tp + self.steps
        col = Tp
        while True:
            self._collect(block=False)
            active = [b for b in range(B) if self.mode[b] in ("sample", "force")]
            waiting = [b for b in range(B) if self.mode[b] == "wait"]
            if not active:
                if not waiting:
                    break
                self._collect(block=True, only=waiting[:1])
                continue
            need = max(self.limits.max_total_tokens - len(self.toks[b]) for b in active + waiting)
            if waiting and cols - col <= need:  # no pause column to spare: wait for the tools first
                self._collect(block=True, only=waiting)
                continue
            tok_in = [self.pad] * B
            sample = [b for b in active if self.mode[b] == "sample"]
            if sample:
                idx = torch.tensor(sample, dtype=torch.long, device=dev)
                k = torch.tensor([self.n_sampled[b] for b in sample], dtype=torch.long, device=dev)
                tok, lp, pol = self.sampler(logits.index_select(0, idx).float(), self.u[idx, k].view(-1, 1))
                for b, t, a, p in zip(sample, tok.view(-1).tolist(), lp.view(-1).tolist(), pol.view(-1).tolist()):
                    self._record(b, t, 1, a, p)
                    self.turn[b].append(t)
                    self.n_sampled[b] += 1
                    tok_in[b] = t
            for b in active:
                if self.mode[b] == "force":
                    t = self.queue[b].pop(0)
                    self._record(b, t, 0, 0.0, 0.0)
                    tok_in[b] = t
            fed = set(active)
            logits = fwd.decode(torch.tensor(tok_in, dtype=torch.long, device=dev).view(B, 1),
                                torch.tensor(self.pos, dtype=torch.long, device=dev), col)
            idle = [b for b in range(B) if b not in fed]
            if idle:
                _hide(fwd, idle, col)
            col += 1
            for b in active:
                self.pos[b] += 1
                if self.mode[b] == "force":
                    if not self.queue[b]:
                        self.mode[b] = "sample"
                else:
                    self._after_sample(b)
        return {key: self._rollout(b) for b, key in enumerate(self.rows)}

    def _record(self, b: int, t: int, m: int, lp: float, pol: float) -> None:
        self.toks[b].append(t)
        self.mask[b].append(m)
        self.lps[b].append(lp)
        self.pols[b].append(pol)

    # ------------------------------------------------------------------ turns
    def _after_sample(self, b: int) -> None:
        """After row b sampled a token: end its turn at the eos or a limit."""
        from posttrain.verifiers.envs import Turn

        lim, ep = self.limits, self.episodes[b]
        last = self.turn[b][-1]
        at_eos = last in self.eos
        if not at_eos and len(self.turn[b]) < lim.max_turn_tokens and len(self.toks[b]) < lim.max_total_tokens:
            return
        body = self.turn[b][:-1] if at_eos else self.turn[b]
        turn = Turn(text=self.tok.decode(body, skip_special_tokens=True), sampled_tokens=len(self.turn[b]))
        ep.turns.append(turn)
        self.mode[b] = "done"
        if not at_eos:
            ep.finish = "length" if len(self.turn[b]) >= lim.max_turn_tokens else "max_tokens"
        else:
            calls = self.env.parse_calls(turn.text, ep)
            if not calls:
                ep.finish = "answer"
            elif len(ep.turns) >= lim.max_turns:
                ep.finish = "max_turns"
            else:
                self.pending[b] = self.runner.submit(self.tools, calls, lim)
                self.mode[b] = "wait"
        if self.mode[b] == "done":
            turn.reward = self.env.turn_reward(ep, turn)

    def _collect(self, block: bool, only: list[int] | None = None) -> None:
        """Answer waiting rows whose tool calls are done (all of `only`, blocking, when `block`)."""
        now = time.monotonic()
        for b in (only if only is not None else range(self.B)):
            if self.mode[b] != "wait":
                continue
            results = self.pending[b].wait() if block else self.pending[b].poll(now)
            if results is None:
                continue
            self.runner.abandon(self.pending[b])
            self.pending[b] = None
            self._append_environment(b, results)

    def _append_environment(self, b: int, results) -> None:
        """The environment's reply to row b's turn, as exactly the tokens the chat template adds for it."""
        ep = self.episodes[b]
        turn = ep.turns[-1]
        turn.results = list(results)
        turn.reward = self.env.turn_reward(ep, turn)
        reply = self.env.respond(ep, turn.results)
        if not reply:
            ep.finish, self.mode[b] = "env", "done"
            return
        before = self.rendered[b] + turn.text + self.eos_text
        messages = ep.messages + [{"role": "assistant", "content": turn.text}] + [dict(m) for m in reply]
        after = render_prompt(self.tok, messages)
        if not after.startswith(before):
            raise ModelError(
                f"multi-turn episodes: the chat template of {getattr(self.tok, 'name_or_path', '?')!r} does not "
                f"render a conversation as a prefix of its continuation (it rewrites earlier turns, or closes an "
                f"assistant turn with something other than its eos {self.eos_text!r}); such templates are refused")
        new = self.tok(after[len(before):], add_special_tokens=False)["input_ids"]
        if not new or len(self.toks[b]) + len(new) + 1 > self.limits.max_total_tokens:
            ep.finish, self.mode[b] = "max_tokens", "done"
            return
        ep.messages, self.rendered[b] = messages, after
        turn.env_tokens = len(new)
        self.env_tokens[b] += len(new)
        self.queue[b], self.turn[b], self.mode[b] = list(new), [], "force"

    def _rollout(self, b: int) -> Rollout:
        ep = self.episodes[b]
        i, j = self.rows[b]
        ended_at_eos = bool(self.toks[b]) and self.mask[b][-1] == 1 and self.toks[b][-1] in self.eos
        if ep.finish == "answer":  # the final answer joins the conversation (a turn with calls already did)
            ep.messages = ep.messages + [{"role": "assistant", "content": ep.final_text}]
        r = Rollout(prompt_ids=list(self.ids[i]), completion_ids=self.toks[b], logprobs=self.lps[b],
                    policy_logprobs=self.pols[b], finish_reason="eos" if ended_at_eos else "length",
                    text=ep.final_text, prompt_index=i, sample_index=j, prompt=self.first_messages(i),
                    completion_mask=self.mask[b])
        r.reward = float(self.env.reward(ep))
        r.extras["episode"] = {**ep.to_dict(), "sampled_tokens": int(sum(self.mask[b])),
                               "env_tokens": self.env_tokens[b], "metrics": env_metrics(self.env, ep)}
        return r

    def first_messages(self, i: int) -> list[dict]:
        return [dict(m) for m in self.first[i]]


def env_metrics(env: Environment, episode) -> dict[str, float]:
    """`env.metrics(episode)` after its reward, checked: a mapping of names to finite numbers (saved in the
    rollout's `extras["episode"]["metrics"]`, averaged by `episode_metrics` as `env/<name>`); anything else is a
    ValueError naming the environment."""
    import math

    got = env.metrics(episode)
    if not isinstance(got, dict) or not all(isinstance(k, str) and isinstance(v, (int, float)) and not
                                            isinstance(v, bool) and math.isfinite(v) for k, v in got.items()):
        raise ValueError(f"environment {env.name!r}: metrics(episode) must return a dict of names to finite numbers, "
                         f"got {got!r}")
    return {k: float(v) for k, v in got.items()}


def episode_metrics(rollouts: Sequence[Rollout]) -> dict[str, float]:
    """The environment's means over a batch of episode rollouts (`posttrain.verifiers.envs.episode_metrics`)."""
    from posttrain.verifiers.envs import episode_metrics as means

    return means([r.extras["episode"] for r in rollouts if "episode" in r.extras])
