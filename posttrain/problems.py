"""Verifiable problems: prompts with a verifier reference, checked before any model loads; the verifier (and/or
reward-model) reward of a run; held-out greedy accuracy against the SFT model.

CPU: `python -c "import posttrain.problems"`; exercised through GRPO (tests/posttrain/trainers/test_grpo.py).

- `split_rows` / `check_problems`: rows of a problem file (schema "verifiable") or of the task's split; a row
  without a reference (`row_reference`: `answer`, else meta.answer / meta.reference) stops naming its row
  (on_bad_rows=error) or is skipped with a count.
- `build_verifier`: a registry spec (auto: the rows' `verifier` field, else the task's `VERIFIER`); `preflight`
  scores the worked solutions of the first PREFLIGHT_ROWS rows, so a verifier that raises stops the run
  before anything trains (one that scores them below 1 is reported, not fatal).
- `tokenize_problems`: prompts rendered and tokenized once (`posttrain.chat`), too-long ones dropped with a count.
- `build_reward` -> `Reward`: the scorers of `posttrain.scoring` (verifier, reward model, or both weighted).
- `load_env` / `build_env_reward`: a multi-turn environment (`<stage>.env`) and its episodes' reward.
- `score_groups` / `gather_groups`: K samples per problem scored as `Group`s (identical completions of a problem
  scored once), gathered over processes in global order; a verifier that raised everywhere stops the run.
- `load_problems`: the problems of a GRPO or distillation run (task, verifier, references, enough of them), checked
  before any model loads; `sample_and_score`: one round of rollouts of a global prompt batch, sampled and scored by
  each process for its positions, gathered.
- `HeldOut`: greedy completions of held-out problems scored by the verifier (eval/accuracy is the pass rate of
  the FIRST term of a composition) and the reward model; the SFT baseline is measured once and kept for resume.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from posttrain import loop, sharding
from posttrain.errors import ConfigError

if TYPE_CHECKING:
    from posttrain.verifiers.envs import Environment, ToolRunner

PREFLIGHT_ROWS = 8  # worked solutions scored before training (a broken verifier stops there)


@dataclass
class Problem:
    """One prompt with its verifier reference; `key` (its row index) seeds its samples."""

    prompt: str | list[dict]  # text or a conversation (posttrain.chat)
    reference: Any
    key: int
    prompt_ids: list[int] = field(default_factory=list)
    env_problem: dict[str, Any] | None = None  # with an environment: the row its `reset` starts an episode from


def env_problem(row: dict[str, Any]) -> dict[str, Any]:
    """A row as an environment's problem: its fields, with `prompt` the question (a conversational row's first user
    message: a task's demonstration rows hold the whole solved conversation) and `answer` its reference."""
    out = {k: v for k, v in row.items() if k not in ("messages", "completion", "train_from")}
    if "messages" in row:
        out["prompt"] = next(m["content"] for m in row["messages"] if m["role"] == "user")
    out["answer"] = row_reference(row)
    return out


def _present(value: Any) -> bool:
    if isinstance(value, str):
        return bool(value.strip())
    if isinstance(value, (dict, list)):
        return bool(value)
    return value is not None


def row_reference(row: dict[str, Any]) -> Any:
    """The verifier reference of a row: `answer`, else meta.answer / meta.reference; None when missing or empty."""
    meta = row.get("meta") if isinstance(row.get("meta"), dict) else {}
    for value in (row.get("answer"), meta.get("answer"), meta.get("reference")):
        if _present(value):
            return value
    return None


def build_verifier(spec: str, options: dict[str, Any], task, rows: list[dict[str, Any]], *, stage: str = "grpo"):
    """The Verifier instance of `spec` (`<stage>.verifier`; auto: the rows' `verifier` field, else the task's
    VERIFIER; none: None) with its keyword `options`; one-line ConfigErrors naming the key."""
    from posttrain.verifiers.registry import get_verifier

    spec = spec.strip()
    if spec == "none":
        return None
    if spec == "auto":
        named = sorted({str(r["verifier"]) for r in rows if r.get("verifier")})
        if len(named) > 1:
            raise ConfigError(f"{stage}.verifier=auto: the problems name several verifiers ({', '.join(named)}); "
                              f"set {stage}.verifier to one spec (e.g. logic dispatches on the reference's family)")
        spec = named[0] if named else (task.VERIFIER or "")
        if not spec:
            raise ConfigError(f"{stage}.verifier=auto but task {task.NAME!r} names no verifier "
                              f"(VERIFIER); set {stage}.verifier, e.g. {stage}.verifier=math")
    try:
        return get_verifier(spec, **options)
    except (ValueError, ImportError, TypeError) as e:
        raise ConfigError(f"{stage}.verifier: {e}") from None


def check_problems(rows: list[dict[str, Any]], source: str, on_bad: str, *,
                   stage: str = "grpo") -> tuple[list[Problem], list[int]]:
    """Problems of `rows` (1-based row numbers in errors); rows without a reference stop or are skipped."""
    problems, skipped = [], []
    for i, row in enumerate(rows):
        ref = row_reference(row)
        if ref is None:
            if on_bad == "error":
                raise ConfigError(f"{source}: row {i + 1}: no reference answer for the verifier (an 'answer' field, "
                                  f"or meta.answer / meta.reference); fix the row or set {stage}.on_bad_rows=skip")
            skipped.append(i + 1)
            continue
        problems.append(Problem(row["prompt"], ref, i))
    return problems, skipped


def preflight(verifier, pool, rows: list[dict[str, Any]], source: str, say, *, stage: str = "grpo") -> None:
    """Score the worked solutions of the first rows: a verifier that raises stops here, with the row."""
    from posttrain.verifiers.runner import VerifierError

    rows = [r for r in rows[:PREFLIGHT_ROWS] if isinstance(r.get("completion"), str) and row_reference(r) is not None]
    if not rows:
        return
    try:
        verdicts = pool.score(verifier, [r["completion"] for r in rows], [row_reference(r) for r in rows])
    except VerifierError as e:
        where = f"the worked solution of {source} row {e.index + 1}" if e.index is not None else "loading"
        raise ConfigError(f"{stage}.verifier {verifier.name!r} raised {e.exc_type} on {where}: {e.message} "
                          "(a bug in the verifier or a malformed reference; nothing was trained)") from None
    low = [(i, v) for i, v in enumerate(verdicts) if v.score < 1.0]
    if low:
        i, v = low[0]
        say(f"[{stage}] note: the verifier scores {len(low)} of {len(rows)} worked solutions below 1 (e.g. {source} "
            f"row {i + 1}: {v.score:.2f}, {v.reason!r}); check that the verifier matches the task's answer format")


def split_rows(task_cfg, split: str, file: str | None, schema: str = "verifiable") -> tuple[list[dict], str]:
    """The rows of a problem file (e.g. grpo.train_file / eval_file; `schema` "prompt": prompts without a
    reference, for a run without a verifier), else of the task's split (the recipe's `task:` section); and where
    they come from."""
    from posttrain import tasks
    from posttrain.data import load_rows

    if file:
        return [dict(r) for r in load_rows(file, schema, tasks.columns(task_cfg), say=print,
                                           split="train" if split == "train" else "test")], file
    return tasks.load_split(task_cfg, split), f"task {task_cfg.name} ({split})"


def tokenize_problems(tokenizer, problems: list[Problem], what: str, max_new_tokens: int, max_length: int,
                      say, *, stage: str = "grpo") -> list[Problem]:
    """Prompts tokenized once (the engine takes ids; the chat template when there is one); a prompt longer than
    max_length - max_new_tokens is dropped, with a count."""
    from posttrain.chat import encode_prompts

    kept = []
    for p, x in zip(problems, encode_prompts(tokenizer, [p.prompt for p in problems])):
        if len(x) + max_new_tokens <= max_length:
            p.prompt_ids = list(x)
            kept.append(p)
    if len(kept) < len(problems):
        say(f"[{stage}] dropped {len(problems) - len(kept)}/{len(problems)} {what} prompts longer than "
            f"model.max_length="
            f"{max_length} - max_new_tokens={max_new_tokens}")
    return kept


class ProblemSet(NamedTuple):
    """What `load_problems` read and checked."""

    verifier: Any  # the Verifier, or None (no verifier: a reward model only, or distillation without a reward)
    train_rows: list[dict[str, Any]]
    train_source: str
    problems: list[Problem]  # training problems
    eval_problems: list[Problem]  # held-out problems (the first max(eval_rows, final_eval_rows) rows)


def load_problems(res, cfg, stage: str, *, schema: str = "verifiable") -> ProblemSet:
    """The problems of a `stage` run (grpo, distill: the fields verifier, verifier_options, train_file, eval_file,
    eval_rows, final_eval_rows, on_bad_rows, prompts_per_step of its config `cfg`), checked before any model
    loads: the task, the verifier spec, a reference per problem when there is a verifier (on_bad_rows; skipped
    rows are counted), enough problems. `schema` "prompt": the files' rows need no reference."""
    from posttrain import tasks

    try:
        task = tasks.get_task(res.task.name)
    except ValueError as e:
        raise ConfigError(f"task.name: {e}") from None
    env_spec = getattr(cfg, "env", "")
    if env_spec:  # an environment's rows: a prompt (and what its reward reads, e.g. an answer), no verifier column
        schema = "prompt"
    train_rows, train_source = split_rows(res.task, "train", cfg.train_file, schema)
    eval_rows, eval_source = split_rows(res.task, "eval", cfg.eval_file, schema)
    eval_rows = eval_rows[: max(cfg.eval_rows, cfg.final_eval_rows)]
    verifier = None if env_spec else build_verifier(cfg.verifier, cfg.verifier_options, task, train_rows, stage=stage)
    if env_spec:  # the environment rewards whole episodes; its problems are the rows themselves
        as_env = lambda rows: [Problem(e["prompt"], e["answer"], i, env_problem=e)  # noqa: E731
                               for i, e in enumerate(map(env_problem, rows))]
        problems, eval_problems = as_env(train_rows), as_env(eval_rows)
    elif verifier is not None:
        problems, skipped = check_problems(train_rows, train_source, cfg.on_bad_rows, stage=stage)
        eval_problems, eval_skipped = check_problems(eval_rows, eval_source, cfg.on_bad_rows, stage=stage)
        for n, what, rows in ((skipped, train_source, train_rows), (eval_skipped, eval_source, eval_rows)):
            if n:  # on every process
                print(f"[{stage}] skipped {len(n)} of {len(rows)} problems of {what} without a reference answer "
                      f"(rows {', '.join(map(str, n[:10]))}{', ...' if len(n) > 10 else ''})")
    else:  # no verifier: no references needed
        problems = [Problem(r["prompt"], None, i) for i, r in enumerate(train_rows)]
        eval_problems = [Problem(r["prompt"], None, i) for i, r in enumerate(eval_rows)]
    if len(problems) < cfg.prompts_per_step:
        raise ConfigError(f"{train_source}: {len(problems)} usable problems, fewer than {stage}.prompts_per_step="
                          f"{cfg.prompts_per_step}")
    return ProblemSet(verifier, train_rows, train_source, problems, eval_problems)


@dataclass
class Reward:
    """The run's reward, through `posttrain.scoring`: the verifier (None: reward model only) and its scorers."""

    verifier: Any
    scorer: Any  # scores training completions: a VerifierScorer, a RewardModelScorer or both in a WeightedScorer
    eval_scorer: Any  # the verifier's, errors scored 0 (held-out evaluation); None without a verifier
    rm_scorer: Any  # None without a reward model
    verifier_parts: set[str]  # reward parts that are verifier verdicts (logged as pass/<part> too)
    correctness: str | None  # the first term of a composition: eval/accuracy's part
    prefix: str  # "verifier/" when a WeightedScorer prefixes its scorers' parts
    env: Environment | None = None  # a multi-turn environment: episodes replace single completions
    runner: ToolRunner | None = None


def build_env_reward(env: Environment, runner: ToolRunner | None) -> Reward:
    """The reward of a run in a multi-turn environment: `env.reward` of each episode (no verifier, no scorer)."""
    return Reward(None, None, None, None, set(), None, "", env, runner)


def load_env(cfg, stage: str) -> Environment | None:
    """The run's multi-turn environment (`<stage>.env` with `<stage>.env_options`), or None when env is empty; a
    bad spec or option is one ConfigError line naming the key."""
    if not cfg.env:
        return None
    from posttrain.verifiers.envs import get_env

    try:
        return get_env(cfg.env, **cfg.env_options)
    except (ValueError, ImportError) as e:
        raise ConfigError(f"{stage}.env: {e}") from None


def build_reward(verifier, pool, rm_dir: Path | None, device, *, timeout_s: float = 0.0, on_error: str = "zero",
                 verifier_weight: float = 1.0, reward_model_weight: float = 1.0) -> Reward:
    """The verifier (None: none) and / or the reward model at `rm_dir` (None: none) as one reward: checks in `pool`
    under `timeout_s` (0: the verifier's own limit); a check that raises scores 0 (on_error "zero") or raises
    ("stop"); both weighted when both are given."""
    from posttrain.scoring import RewardModelScorer, VerifierScorer, WeightedScorer

    timeout = timeout_s or None
    vscorer = eval_scorer = None
    if verifier is not None:
        vscorer = VerifierScorer(verifier, pool=pool, timeout_s=timeout, name="verifier",
                                 on_error="zero" if on_error == "zero" else "raise")
        eval_scorer = VerifierScorer(verifier, pool=pool, timeout_s=timeout, name="verifier", on_error="zero")
    rm_scorer = RewardModelScorer(rm_dir, device=device, name="rm") if rm_dir is not None else None
    if vscorer is not None and rm_scorer is not None:
        scorer = WeightedScorer([(vscorer, verifier_weight), (rm_scorer, reward_model_weight)])
    else:
        scorer = vscorer if vscorer is not None else rm_scorer
    labels = [label for label, _, _ in getattr(verifier, "parts", [])]  # a composition's terms
    prefix = "verifier/" if rm_scorer is not None else ""
    return Reward(verifier, scorer, eval_scorer, rm_scorer,
                  ({"verifier"} | {prefix + p for p in labels}) if verifier is not None else set(),
                  labels[0] if labels else None, prefix)


# ----------------------------------------------------------------------------- groups of samples
@dataclass
class Group:
    """One prompt's K samples, scored."""

    problem: Problem
    rollouts: list  # list[Rollout], K
    rewards: list[float]
    reasons: list[str]
    parts: dict[str, list[float]]  # reward part -> K values


def score_groups(reward: Reward, problems: list[Problem], out: list, K: int,
                 step: int) -> tuple[list[Group], str | None, int]:
    """This process's samples scored: (groups, the message of a verifier error under on_verifier_error=stop, the
    number of distinct completions scored). Identical completions of a prompt are scored once (verifiers and
    reward models are deterministic; a confident policy samples many duplicates, and a sandboxed check is costly)."""
    from posttrain.verifiers.runner import VerifierError

    if not problems:
        return [], None, 0
    first: dict[tuple[int, str], int] = {}
    slot = [first.setdefault((problems[i // K].key, r.text), len(first)) for i, r in enumerate(out)]
    uniq = list(first)  # (problem key, text) in first-seen order
    by_key = {p.key: p for p in problems}
    try:
        su = reward.scorer.score([by_key[k].prompt for k, _ in uniq], [t for _, t in uniq],
                                 [by_key[k].reference for k, _ in uniq] if reward.verifier is not None else None)
    except VerifierError as e:  # on_verifier_error=stop: raised after the gather, by every process
        row = uniq[e.index][0] + 1 if e.index is not None and reward.rm_scorer is None else "?"
        return [], (f"verifier {reward.verifier.name!r} raised {e.exc_type} at step {step + 1} on a completion of "
                    f"training problem row {row}: {e.message} (on_verifier_error=stop)"), 0
    groups = []
    for g, p in enumerate(problems):
        sl = [slot[g * K + j] for j in range(K)]
        groups.append(Group(p, out[g * K:(g + 1) * K], [su.rewards[i] for i in sl], [su.reasons[i] for i in sl],
                            {k: [v[i] for i in sl] for k, v in su.parts.items()}))
    return groups, None, len(uniq)


def gather_groups(reward: Reward, accelerator, positions: list[int],
                  scored: tuple[list[Group], str | None, int],
                  step: int) -> tuple[list[Group], int]:
    """Every process's `score_groups` of a round: the groups in global order, the distinct completions scored.
    A verifier error under on_verifier_error=stop on any process stops every process; so does a round where
    every check raised (that reward carries no signal)."""
    groups, error, n = scored
    shards = sharding.gather_rows(accelerator, [(list(zip(positions, groups)), error, n)],
                                  [accelerator.process_index])
    errors = [e for _, e, _ in shards if e]
    if errors:
        raise loop.TrainingError(errors[0])
    groups = [g for _, g in sorted((x for sh, _, _ in shards for x in sh), key=lambda t: t[0])]
    reasons = [x for g in groups for x in g.reasons]
    if reward.verifier is not None and all("verifier error:" in x for x in reasons):
        raise loop.TrainingError(f"verifier {reward.verifier.name!r} raised on every completion of step {step + 1} "
                                 f"({reasons[0]}); the reward is broken")
    return groups, sum(n for _, _, n in shards)


class Round(NamedTuple):
    """One round of rollouts, scored and gathered (`sample_and_score`)."""

    groups: list[Group]  # every process's, in global order
    scored: int  # distinct completions scored (duplicates reuse a score; 0 without a reward)
    sample_s: float  # this process's sampling time
    score_s: float  # this process's scoring and gathering time


def sample_and_score(accelerator, model, tokenizer, problems: list[Problem], idx: list[int], params,
                     reward: Reward | None, step: int) -> Round:
    """The round's global prompt batch problems[idx], params.n samples each: process r samples and scores positions
    r, r + W, ... (a group never spans processes; a process with no position samples nothing), then the groups
    are gathered, so every process holds all of them in global order. Without a `reward` the groups carry reward
    0 and no reasons."""
    from posttrain.rollout import generate

    K = params.n
    positions = sharding.positions(len(idx), accelerator.process_index, accelerator.num_processes)
    local = [problems[idx[i]] for i in positions]
    t0 = time.time()
    if reward is not None and reward.env is not None:  # multi-turn episodes, rewarded by the environment
        from posttrain.rollout.multiturn import generate_episodes

        out = generate_episodes(model, tokenizer, reward.env, [p.env_problem for p in local], params,
                                prompt_keys=[p.key for p in local], runner=reward.runner) if local else []
        t1 = time.time()
        episodes = [Group(p, out[g * K:(g + 1) * K], [r.reward for r in out[g * K:(g + 1) * K]],
                          [r.extras["episode"]["finish"] for r in out[g * K:(g + 1) * K]], {})
                    for g, p in enumerate(local)]
        groups = sharding.gather_rows(accelerator, episodes, positions)
        return Round(groups, len(out), t1 - t0, time.time() - t1)
    out = generate(model, tokenizer, [p.prompt_ids for p in local], params,
                   prompt_keys=[p.key for p in local]) if local else []
    t1 = time.time()
    if reward is not None:
        groups, scored = gather_groups(reward, accelerator, positions, score_groups(reward, local, out, K, step), step)
    else:
        unscored = [Group(p, out[g * K:(g + 1) * K], [0.0] * K, [""] * K, {}) for g, p in enumerate(local)]
        groups, scored = sharding.gather_rows(accelerator, unscored, positions), 0
    return Round(groups, scored, t1 - t0, time.time() - t1)


# ----------------------------------------------------------------------------- held-out evaluation
@dataclass
class HeldOut:
    """Greedy completions of held-out problems, scored by the verifier (and the reward model): n_eval of them every
    eval_every steps, n_final before and after training (the SFT vs trained comparison)."""

    problems: list[Problem]
    reward: Reward
    max_new_tokens: int
    n_eval: int
    n_final: int
    stage: str = "grpo"
    start: str = "SFT"  # what the model before training is called in the console ("base" under model.start_from=base)

    def evaluate(self, policy, tokenizer, n: int) -> dict[str, Any]:
        """Greedy completions of the first n problems: texts, lengths, truncation, verifier and reward-model scores."""
        from posttrain.loop import Progress
        from posttrain.rollout import SamplingParams, generate

        problems = self.problems[:n]
        if self.reward.env is not None:
            return self.evaluate_episodes(policy, tokenizer, problems)
        rollouts = generate(policy, tokenizer, [p.prompt_ids for p in problems],
                            SamplingParams(n=1, max_new_tokens=self.max_new_tokens, greedy=True),
                            prompt_keys=[p.key for p in problems],
                            progress=Progress(f"[{self.stage}] held-out eval"))
        texts, prompts = [r.text for r in rollouts], [p.prompt for p in problems]
        ev: dict[str, Any] = {"texts": texts, "lengths": [len(r.completion_ids) for r in rollouts],
                              "truncated": [r.finish_reason == "length" for r in rollouts]}
        if self.reward.eval_scorer is not None:
            sr = self.reward.eval_scorer.score(prompts, texts, [p.reference for p in problems])
            ev.update(reward=sr.rewards, parts=sr.parts, reasons=sr.reasons)
        if self.reward.rm_scorer is not None:
            ev["rm"] = self.reward.rm_scorer.score(prompts, texts).rewards
        return ev

    def evaluate_episodes(self, policy, tokenizer, problems: list[Problem]) -> dict[str, Any]:
        """Greedy episodes of held-out problems in the environment: final answers, rewards, whole transcripts."""
        from posttrain.rollout.multiturn import generate_episodes

        rollouts = generate_episodes(policy, tokenizer, self.reward.env, [p.env_problem for p in problems],
                                     greedy=True, prompt_keys=[p.key for p in problems], runner=self.reward.runner)
        return {"texts": [r.text for r in rollouts], "lengths": [len(r.completion_ids) for r in rollouts],
                "truncated": [r.finish_reason == "length" for r in rollouts],
                "reward": [r.reward for r in rollouts], "parts": {}, "reasons": [r.extras["episode"]["finish"]
                                                                              for r in rollouts],
                "episodes": [r.extras["episode"] for r in rollouts],
                "transcripts": [tokenizer.decode(r.completion_ids) for r in rollouts]}

    def summarise(self, ev: dict[str, Any], n: int) -> dict[str, float]:
        """eval/* metrics of the first n rows of an `evaluate` result."""
        n = min(n, len(ev["texts"]))
        if n == 0:
            return {}
        m = {"eval/length": sum(ev["lengths"][:n]) / n, "eval/truncated": sum(ev["truncated"][:n]) / n}
        if "reward" in ev:
            m["eval/reward"] = sum(ev["reward"][:n]) / n
            m["eval/pass"] = sum(x >= 1.0 for x in ev["reward"][:n]) / n
            for label, values in ev["parts"].items():
                if label != "verifier":
                    m[f"eval/pass/{label}"] = sum(x >= 1.0 for x in values[:n]) / n
            src = ev["parts"][self.reward.correctness] if self.reward.correctness else ev["reward"]
            m["eval/accuracy"] = sum(x >= 1.0 for x in src[:n]) / n
        if "rm" in ev:
            m["eval/rm"] = sum(ev["rm"][:n]) / n
        if "episodes" in ev:  # env/turns, env/tool_calls, ... of the held-out episodes
            from posttrain.verifiers.envs import episode_metrics

            m.update({f"eval/{k}": v for k, v in episode_metrics(ev["episodes"][:n]).items()})
        return m

    def log_eval(self, policy, tokenizer, metrics: loop.MetricsLog, step: int, say) -> None:
        """The periodic evaluation: the first n_eval problems, logged at `step` and said in one line."""
        summary = self.summarise(self.evaluate(policy, tokenizer, self.n_eval), self.n_eval)
        metrics.log(step, summary, console=False)
        say(f"[{self.stage}] step {step} eval, {self.n_eval} held-out problems: "
            + ", ".join(f"{k.removeprefix('eval/')} {v:.3f}" for k, v in summary.items()))

    def samples(self, ev: dict[str, Any]) -> list[dict[str, str]]:
        texts = ev.get("transcripts", ev["texts"])  # an episode: every turn, tool results included
        return [{"prompt": p.prompt, "completion": t} for p, t in zip(self.problems[:10], texts)]

    def sft_baseline(self, policy, tokenizer, path: Path, start: int, metrics: loop.MetricsLog, say) -> dict:
        """The SFT model's numbers: measured before step 1 (logged at step 0), read back from `path` on resume."""
        if not (self.n_final or self.n_eval):
            return {}
        if start > 0:
            return json.loads(path.read_text()) if path.is_file() else {}
        t0 = time.time()
        ev = self.evaluate(policy, tokenizer, max(self.n_final, self.n_eval))
        baseline = {"metrics": self.summarise(ev, self.n_final or self.n_eval),
                    "eval_metrics": self.summarise(ev, self.n_eval), "samples": self.samples(ev)}
        loop.write_json(path, baseline)
        if self.n_eval:
            metrics.log(0, baseline["eval_metrics"], console=False)
        key = "eval/accuracy" if "eval/accuracy" in baseline["metrics"] else "eval/rm"
        say(f"[{self.stage}] {self.start} model, greedy, {self.n_final or self.n_eval} held-out problems: {key.removeprefix('eval/')} "
            f"{baseline['metrics'][key]:.3f} ({time.time() - t0:.1f}s)")
        return baseline

    def compare(self, policy, tokenizer, baseline: dict, metrics: loop.MetricsLog, step: int, say) -> dict:
        """After training: the trained policy's numbers against the SFT model's (eval.json's rows, sft, grpo)."""
        if not (self.n_final or self.n_eval):
            return {}
        n = self.n_final or self.n_eval
        ev = self.evaluate(policy, tokenizer, max(n, self.n_eval))
        after = self.summarise(ev, n)
        if self.n_eval:
            metrics.log(step, self.summarise(ev, self.n_eval), console=False)
        before = baseline.get("metrics", {})
        key = "eval/accuracy" if "eval/accuracy" in after else "eval/rm"
        was = f"{self.start} {before[key]:.3f} -> " if key in before else ""
        say(f"[{self.stage}] held-out greedy {key.removeprefix('eval/')} on {n} problems: {was}{self.stage.upper()} "
            f"{after[key]:.3f}")
        return {"rows": n, "sft": before, self.stage: after, "samples": self.samples(ev)}
