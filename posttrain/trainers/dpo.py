"""Direct Preference Optimization (Rafailov et al. 2023) on preference pairs; IPO / hinge variants, an online mode.

CPU:        posttrain dpo --recipe tiny-summarize        (from nothing: SFT, pairs, DPO, eval; see the recipe header)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain dpo --recipe tiny-summarize model.path=/path/to/hf-model

Reads top to bottom: load pairs (the prefs stage output, or dpo.train_file) and check them;
load the SFT model; compute the reference log-probs of the pairs ONCE with it (and the SFT
model's greedy completions of the held-out prompts, the win-rate baseline); then train that
same model as the policy, loop { batch of pairs -> one forward -> dpo_loss -> optimizer step ->
log -> eval (held-out pairs, gold, proxy RM, KL) -> checkpoint }; save final/ as a HF directory;
evaluate against the SFT model and print the gold win-rate.

Details, and where they come from:
- Loss: `posttrain.losses.dpo_loss` (sigmoid DPO with conservative label smoothing, IPO, SLiC
  hinge). Log-probs are sums over completion tokens, eos included; for IPO they are length-
  averaged (sum / tokens) for policy and reference alike, as TRL does (Azar et al. 2023 define
  IPO on sequence log-likelihoods; the average keeps its 1/(2 beta) target per token).
- One forward for both sides, and the prompt computed once (`share_prompt`, default): each pair is
  ONE row, prompt + chosen + rejected, with a 4D attention mask under which the rejected tokens see
  the prompt and themselves but not the chosen tokens, and positions that restart after the prompt
  (`preferences.collate_shared_prompt`, `logprobs.packed_logprobs`). Each side's log-probs equal
  those of its own prompt + completion row (tested to fp32 rounding); the prompt's tokens go through
  the model once instead of twice (prefix sharing). share_prompt=false concatenates chosen rows then
  rejected rows along the batch instead (TRL's `concatenated_forward`), for models that take no 4D
  mask. Padding never changes a row's numbers (`posttrain.logprobs` positions count real tokens only).
- Reference (`reference`): "precomputed" (default) runs the SFT model over every training pair
  the run will draw (in online mode: those of the first online_every steps) and every held-out
  pair before the first update and keeps only the (N,) log-prob sums, so no reference model sits
  in memory while training (TRL's `precompute_ref_log_probs`). The policy starts as
  that very model, so nothing is loaded twice. "live" keeps a frozen copy and recomputes the
  reference per batch (same numbers, more memory and time; useful for very large pair sets).
  The KL eval and online DPO need reference log-probs of NEW sequences: with "precomputed" the
  reference is loaded from disk for that moment and freed again.
- `chosen_nll_weight` > 0 adds the per-token NLL of the chosen completions: RPO (Pang et al. 2024,
  "Iterative Reasoning Preference Optimization"; TRL's `rpo_alpha`). Off by default.
- Bad rows (`on_bad_rows`): chosen == rejected, an empty side, prompt + completion longer than
  model.max_length: "error" stops before anything runs, naming the file and row; "skip" drops
  them and prints a count per reason with row numbers.
- Non-finite loss or gradient: `loop.optimizer_step` raises before the update; weights are also
  checked before each checkpoint, so a blow-up that only shows in the weights (a huge learning
  rate) is caught before it can overwrite a checkpoint. The error names the step and the last
  good checkpoint, which is left intact (resume=true continues from it, e.g. with a lower lr).
- Eval every `eval_every` steps, logged to metrics.jsonl: held-out pair loss / implicit-reward
  accuracy; for tasks with a gold metric, the policy's greedy completions of `eval_rows` held-out
  prompts scored by gold (gold/reward = quality - 2 * distance from the length band, gold/quality,
  gold/in_band, gold/length, gold/win_rate vs the SFT model, ties half), by the proxy reward model
  when one exists (proxy/reward), and kl = mean sequence KL(policy || reference) estimated on the
  policy's own temperature-1 samples (`evaluation.kl_to_reference`). At the end the gold and proxy
  curves are plotted over steps and against sqrt(KL): the over-optimisation picture of Gao et al.
  2022 (`overoptimization.png`).
- Online DPO (`online=true`): the first `online_every` steps train on the offline pairs; then every
  `online_every` steps `online_prompts` training prompts are sampled `online_samples` times from the
  current policy (rollout engine, seeded by the refresh index), labelled by the gold preference or
  the reward model (`online_labeler`), paired as the prefs stage does (`preferences.form_pairs`),
  and the next `online_every` steps train on those pairs only. This is a batched form of online
  AI-feedback DPO (Guo et al. 2024, "Direct Language Model Alignment from Online AI Feedback"),
  which labels fresh pairs at every step. The current pool is saved in each checkpoint, so resume
  is exact.
"""
from __future__ import annotations

import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch

from posttrain import loop
from posttrain.config import ConfigError, Resolved, save_resolved
from posttrain.logprobs import masked_sum, packed_logprobs, sequence_logprobs
from posttrain.losses import dpo_loss
from posttrain.preferences import TokenizedPair, collate_pairs


@dataclass
class DPOConfig:
    train_file: str | None = None
    """Preference file (JSONL/JSON/Parquet: prompt, chosen, rejected); empty: the prefs stage output (sampled)."""
    eval_file: str | None = None
    """Held-out preference file; empty: the prefs stage's eval pairs (or 5% of train_file)."""
    beta: float = 0.1
    """KL strength: implicit reward = beta * (log pi - log pi_ref)."""
    loss_type: Literal["sigmoid", "ipo", "hinge"] = "sigmoid"
    """sigmoid: DPO; ipo: IPO on length-averaged log-probs; hinge: SLiC-HF calibration loss."""
    label_smoothing: float = 0.0
    """Conservative DPO: assumed probability that a label is flipped (sigmoid only, <= 0.5)."""
    chosen_nll_weight: float = 0.0
    """RPO (Pang et al. 2024): add this weight times the per-token NLL of the chosen completions (TRL's rpo_alpha)."""
    share_prompt: bool = True
    """Prefix sharing: one row per pair (prompt, chosen, rejected; rejected masked off chosen), prompt computed once."""
    reference: Literal["precomputed", "live"] = "precomputed"
    """precomputed: reference log-probs once before training, no reference model in memory; live: a frozen copy."""
    lr: float = 1e-4
    """Peak learning rate (AdamW)."""
    weight_decay: float = 0.0
    """AdamW weight decay (not applied to norms and embeddings)."""
    batch_size: int = 32
    """Pairs per optimizer step (global, across processes)."""
    micro_batch_size: int = 0
    """Pairs per forward pass (each is 2 rows: chosen and rejected); 0 means batch_size."""
    max_steps: int = 200
    """Optimizer steps."""
    warmup_steps: int = 10
    """Linear warmup steps."""
    schedule: Literal["cosine", "linear", "constant"] = "linear"
    """Learning-rate schedule after warmup."""
    min_lr_ratio: float = 0.0
    """Final learning rate as a fraction of the peak (cosine / linear)."""
    max_grad_norm: float = 1.0
    """Gradient clipping norm (0 disables)."""
    log_every: int = 10
    """Steps between metric lines."""
    eval_every: int = 50
    """Steps between evaluations (held-out pairs, gold, proxy RM, KL); 0: only at the end."""
    eval_rows: int = 100
    """Held-out prompts for the periodic gold / proxy / KL evaluation."""
    eval_pairs: int = 200
    """Held-out pairs for the periodic implicit-reward accuracy."""
    save_every: int = 100
    """Steps between checkpoints (0: only at the end)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (oldest deleted first)."""
    final_eval_rows: int = 200
    """Held-out prompts for the final comparison with the SFT model (0 skips it)."""
    max_new_tokens: int = 64
    """Generation budget for evaluation and online sampling."""
    proxy_rm: str = "auto"
    """Proxy reward model: auto (runs/<recipe>/rm/final if it exists), none, train (run `rm` first) or a path."""
    online: bool = False
    """Online DPO: regenerate pairs from the current policy every online_every steps."""
    online_every: int = 20
    """Steps between pair regenerations in online mode."""
    online_labeler: Literal["gold", "rm"] = "gold"
    """Who labels online pairs: the task's gold preference or the reward model."""
    online_prompts: int = 128
    """Training prompts sampled per regeneration."""
    online_samples: int = 4
    """Completions per prompt per regeneration."""
    online_pairs_per_prompt: int = 2
    """Pairs per prompt per regeneration (as prefs.pairs_per_prompt: best vs worst, then vs the runner-up, ...)."""
    online_temperature: float = 1.0
    """Sampling temperature of online generation."""
    on_bad_rows: Literal["error", "skip"] = "error"
    """Bad pairs (chosen == rejected, empty side, too long): stop with the file and row, or skip with a count."""
    seed: int = 0
    """Seed of data order, online sampling and init-time randomness."""
    resume: bool = False
    """Continue from the newest checkpoint in the run directory."""


# ----------------------------------------------------------------------------- log-probs of pairs
def pair_logps(model, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Summed completion log-probs (2B,) and completion token counts (2B,) of a `collate_pairs` batch,
    chosen first then rejected, in either layout (two rows per pair, or one shared-prompt row per pair).

    ONE forward over chosen and rejected together; differentiable under autograd.
    """
    if "allowed" in batch:  # shared prompt: one row per pair, prompt + chosen + rejected
        lp = packed_logprobs(model, batch["input_ids"], batch["position_ids"], batch["allowed"],
                             batch["pred_index"], batch["targets"], batch["target_mask"])  # (B, Lc + Lr)
        Lc = int(batch["chosen_cols"])
        cm = batch["target_mask"].to(lp.device, lp.dtype)
        return (torch.cat([lp[:, :Lc].sum(-1), lp[:, Lc:].sum(-1)]),
                torch.cat([cm[:, :Lc].sum(-1), cm[:, Lc:].sum(-1)]))  # (2B,), (2B,)
    logps, _ = sequence_logprobs(model, batch["input_ids"], batch["attention_mask"], batch["completion_mask"])  # (2B, T)
    cm = batch["completion_mask"].to(logps.device)
    return masked_sum(logps, cm, -1), cm.sum(-1).to(logps.dtype)  # (2B,), (2B,)


@torch.no_grad()
def reference_logps(model, pairs: list[TokenizedPair], pad_id: int, micro_batch_size: int,
                    share_prompt: bool = True) -> dict[str, torch.Tensor]:
    """{"chosen", "rejected", "chosen_tokens", "rejected_tokens"}: (N,) tensors on CPU, one entry per pair."""
    was_training = model.training
    model.eval()
    out: dict[str, list[torch.Tensor]] = {"chosen": [], "rejected": [], "chosen_tokens": [], "rejected_tokens": []}
    for chunk in loop.chunks(pairs, micro_batch_size):
        s, n = pair_logps(model, collate_pairs(chunk, pad_id, share_prompt))
        b = len(chunk)
        out["chosen"].append(s[:b].cpu())
        out["rejected"].append(s[b:].cpu())
        out["chosen_tokens"].append(n[:b].cpu())
        out["rejected_tokens"].append(n[b:].cpu())
    model.train(was_training)
    if not pairs:
        return {k: torch.zeros(0) for k in out}
    return {k: torch.cat(v) for k, v in out.items()}


def pair_loss(cfg: DPOConfig, policy_logps: torch.Tensor, policy_tokens: torch.Tensor,
              ref: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
    """`dpo_loss` of one micro-batch: policy (2B,) sums + token counts, reference {chosen, rejected, *_tokens} (B,)."""
    B = policy_logps.shape[0] // 2
    pc, pr = policy_logps[:B], policy_logps[B:]  # (B,), (B,)
    rc, rr = ref["chosen"].to(pc.device), ref["rejected"].to(pc.device)  # (B,), (B,)
    if cfg.loss_type == "ipo":  # length-averaged log-probs for policy and reference (TRL)
        pc, pr = pc / policy_tokens[:B], pr / policy_tokens[B:]
        rc, rr = rc / ref["chosen_tokens"].to(pc.device), rr / ref["rejected_tokens"].to(pc.device)
    loss, metrics = dpo_loss(pc, pr, rc, rr, beta=cfg.beta, loss_type=cfg.loss_type,
                             label_smoothing=cfg.label_smoothing)
    if cfg.chosen_nll_weight:
        nll = -(policy_logps[:B] / policy_tokens[:B].clamp(min=1)).mean()  # per-token NLL of chosen, mean over pairs
        loss = loss + cfg.chosen_nll_weight * nll
        metrics["nll/chosen"] = float(nll.detach())
    return loss, metrics


def _select(ref: dict[str, torch.Tensor], idx: list[int]) -> dict[str, torch.Tensor]:
    t = torch.as_tensor(idx, dtype=torch.long)
    return {k: v[t] for k, v in ref.items()}


@torch.no_grad()
def heldout_pair_metrics(cfg: DPOConfig, model, pairs: list[TokenizedPair], ref: dict[str, torch.Tensor] | None,
                         ref_model, pad_id: int, micro: int) -> dict[str, float]:
    """Mean loss and implicit-reward metrics over held-out pairs (reference precomputed or live)."""
    if not pairs:
        return {}
    model.eval()
    sums: dict[str, float] = {}
    for start in range(0, len(pairs), micro):
        chunk = pairs[start:start + micro]
        batch = collate_pairs(chunk, pad_id, cfg.share_prompt)
        s, n = pair_logps(model, batch)
        r = _select(ref, list(range(start, start + len(chunk)))) if ref is not None else \
            _ref_from_model(ref_model, batch, len(chunk))
        loss, m = pair_loss(cfg, s, n, r)
        m["loss"] = float(loss)
        for k, v in m.items():
            sums[k] = sums.get(k, 0.0) + v * len(chunk)
    return {f"eval/{k}": v / len(pairs) for k, v in sums.items()}


@torch.no_grad()
def _ref_from_model(ref_model, batch: dict[str, torch.Tensor], B: int) -> dict[str, torch.Tensor]:
    s, n = pair_logps(ref_model, batch)
    return {"chosen": s[:B], "rejected": s[B:], "chosen_tokens": n[:B], "rejected_tokens": n[B:]}


def _weights_finite(model) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


# ----------------------------------------------------------------------------- data
def resolve_proxy_rm(res: Resolved, ensure, spec: str, need: bool) -> Path | None:
    """The reward-model directory for proxy scores (see DPOConfig.proxy_rm); `need`: online_labeler=rm."""
    from posttrain.models import is_model_dir

    if spec not in ("auto", "none", "train"):
        if not is_model_dir(spec):
            raise ConfigError(f"proxy_rm {spec!r} is not a reward-model directory; give auto, none, train or a path")
        return Path(spec)
    if spec == "train" or need:
        return ensure("rm")
    if spec == "auto":
        final = res.stage_dir("rm") / "final"
        return final if is_model_dir(final) else None
    return None


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """Train the SFT model with DPO on preference pairs; returns the final model directory."""
    from posttrain import evaluation, preferences, tasks
    from posttrain.models import load_model, load_tokenizer, maybe_lora, reference_view, save_model
    from posttrain.scoring import RewardModelScorer

    cfg: DPOConfig = res.stage_cfg
    if cfg.online and cfg.online_every < 1:
        raise ConfigError(f"dpo.online_every must be >= 1, got {cfg.online_every}")
    if cfg.label_smoothing and cfg.loss_type != "sigmoid":
        raise ConfigError(f"dpo.label_smoothing applies to loss_type=sigmoid only (got loss_type={cfg.loss_type})")
    if not 0.0 <= cfg.label_smoothing <= 0.5 or cfg.beta <= 0:
        raise ConfigError("dpo.beta must be > 0 and dpo.label_smoothing in [0, 0.5]")
    run_dir = res.stage_dir()
    say_all = print

    # Data first: a bad row must stop the run before the run dir changes.
    train_rows, eval_rows_pairs, source, eval_source = preferences.training_pairs(
        ensure, cfg.train_file, cfg.eval_file, seed=cfg.seed)
    if cfg.on_bad_rows == "error":  # fail fast on what needs no tokenizer, before SFT may have to run
        preferences.check_pairs(train_rows, source, "error")
        preferences.check_pairs(eval_rows_pairs[: cfg.eval_pairs], eval_source, "error")
    task = tasks.get_task(res.task.name)
    has_gold = tasks.has_gold_preference(task)
    # gold evaluation needs each held-out prompt's task meta (a task.eval_file may not carry it)
    eval_prompts = [r for r in tasks.load_split(res.task, "eval") if r.get("meta")] if has_gold else []
    if cfg.online and cfg.online_labeler == "gold" and not has_gold:
        raise ConfigError(f"dpo.online_labeler=gold needs a task with a gold preference; {res.task.name!r} has none")
    online_rows = tasks.load_split(res.task, "train") if cfg.online else []
    sft_dir = ensure("sft")
    tokenizer = load_tokenizer(sft_dir, res.model)
    pad_id = tokenizer.pad_token_id
    _, train_pairs, bad = preferences.check_pairs(train_rows, source, cfg.on_bad_rows, tokenizer, res.model.max_length)
    if bad.count:
        say_all(f"[dpo] {bad.summary()}")
    _, eval_pairs, bad = preferences.check_pairs(eval_rows_pairs[: cfg.eval_pairs], eval_source, cfg.on_bad_rows,
                                                 tokenizer, res.model.max_length)
    if bad.count:
        say_all(f"[dpo] held-out pairs: {bad.summary()}")
    if len(train_pairs) < cfg.batch_size:
        raise loop.TrainingError(f"only {len(train_pairs)} usable preference pairs in {source}, fewer than "
                                 f"batch_size={cfg.batch_size}")
    rm_dir = resolve_proxy_rm(res, ensure, cfg.proxy_rm, cfg.online and cfg.online_labeler == "rm")

    accelerator = loop.setup(cfg.seed, res.run.threads)
    main = accelerator.is_main_process
    say = print if main else (lambda *a, **k: None)
    if main:
        loop.prepare_run_dir(run_dir, cfg.resume, say)
        save_resolved(res, run_dir / "config.yaml")
    accelerator.wait_for_everyone()

    micro = cfg.micro_batch_size or cfg.batch_size
    per_process = max(1, cfg.batch_size // accelerator.num_processes)
    n_eval_gen = max(cfg.eval_rows, cfg.final_eval_rows) if has_gold else 0
    gen_rows = eval_prompts[:n_eval_gen]

    # The SFT model: first the reference (log-probs of every pair, the SFT baseline completions),
    # then, unchanged, the policy. No second copy unless reference=live.
    t0 = time.time()
    model = maybe_lora(res, load_model(sft_dir, res.model.dtype, device=accelerator.device), say)  # LoRA: adapters start at 0
    ref_train = ref_eval = None
    ref_model = None
    if cfg.reference == "precomputed":
        # Only the pairs this run will draw (online mode uses the offline pairs for its first
        # online_every steps only); the others get NaN, which would stop the run if ever used.
        offline_steps = min(cfg.max_steps, cfg.online_every) if cfg.online else cfg.max_steps
        used = sorted({i for s in range(offline_steps) for i in loop.batch_indices(len(train_pairs), cfg.batch_size,
                                                                                     cfg.seed, s)})
        ref_used = reference_logps(model, [train_pairs[i] for i in used], pad_id, micro, cfg.share_prompt)
        ref_train = {k: torch.full((len(train_pairs),), float("nan")).index_copy(0, torch.tensor(used), v)
                     for k, v in ref_used.items()}
        ref_eval = reference_logps(model, eval_pairs, pad_id, micro, cfg.share_prompt)
        say(f"[dpo] reference log-probs of {len(used)} training and {len(eval_pairs)} held-out pairs "
            f"precomputed in {time.time() - t0:.1f}s; no reference model is kept in memory")
    else:
        ref_model = reference_view(model) if res.use_lora else \
            load_model(sft_dir, res.model.dtype, device=accelerator.device).eval().requires_grad_(False)
    baseline = evaluation.complete(model, tokenizer, [r["prompt"] for r in gen_rows],
                                   max_new_tokens=cfg.max_new_tokens) if (gen_rows and main) else []
    proxy = RewardModelScorer(rm_dir, device=accelerator.device) if (rm_dir is not None and main) else None
    if rm_dir is not None:
        say(f"[dpo] proxy reward model: {rm_dir}")

    def reference_for_eval():
        """The reference model for KL / online labelling: the live copy, the policy with its LoRA adapters
        off (no copy), or loaded from disk for now."""
        if ref_model is not None:
            return ref_model
        if res.use_lora:
            return reference_view(accelerator.unwrap_model(model))
        return load_model(sft_dir, res.model.dtype, device=accelerator.device).eval()

    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps, cfg.schedule, cfg.min_lr_ratio)
    model, optimizer = accelerator.prepare(model, optimizer)
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.MetricsLog(run_dir / "metrics.jsonl", cfg.max_steps, main, res.run.quiet, prefix="[dpo] ")

    # The pool of pairs the batches come from: the offline pairs, replaced in online mode.
    pool = {"pairs": train_pairs, "ref": ref_train, "start": 0, "gen": 0}
    start = 0
    if cfg.resume:
        last = ckpt.latest()
        if last is None:
            say(f"[dpo] resume=true but no checkpoint in {ckpt.dir}; starting from step 0")
        else:
            state = ckpt.load(last, model, optimizer, scheduler)
            start = state["step"]
            if state["extra"].get("online_pool") is not None:  # an online pool (the offline one is rebuilt above)
                saved = state["extra"]["online_pool"]
                pool = {"pairs": [TokenizedPair(**p) for p in saved["pairs"]], "ref": saved["ref"],
                        "start": saved["start"], "gen": saved["gen"]}
            metrics.truncate_after(start)
            say(f"[dpo] resumed from {last} at step {start}")

    def refresh_pool(step: int) -> dict[str, Any]:
        """Online DPO: fresh pairs from the current policy, labelled by gold or the RM (see module docstring)."""
        gen = step // cfg.online_every
        rng = random.Random(f"online:{cfg.seed}:{gen}")
        idx = rng.sample(range(len(online_rows)), min(cfg.online_prompts, len(online_rows)))
        rows = [online_rows[i] for i in idx]
        if cfg.online_labeler == "gold":
            labeler = preferences.gold_labeler(res.task.name)
        else:
            labeler = preferences.scorer_labeler(proxy if proxy is not None else RewardModelScorer(rm_dir))
        policy = accelerator.unwrap_model(model)
        new_rows, st = preferences.sample_pairs(
            policy, tokenizer, rows, labeler, prompt_keys=idx, samples_per_prompt=cfg.online_samples,
            pairs_per_prompt=cfg.online_pairs_per_prompt, temperature=cfg.online_temperature,
            max_new_tokens=cfg.max_new_tokens, seed=cfg.seed * 1_000_003 + gen, strategy=f"online-{cfg.online_labeler}")
        for i, r in enumerate(new_rows):
            r["_row"] = i + 1
        _, new_pairs, _ = preferences.check_pairs(new_rows, f"online pairs (step {step})", "skip", tokenizer,
                                                  res.model.max_length)
        ref = None
        if cfg.reference == "precomputed":
            reference = reference_for_eval()
            ref = reference_logps(reference, new_pairs, pad_id, micro, cfg.share_prompt)
            del reference
        metrics.log(step, {"online/pairs": len(new_pairs), "online/prompts_all_tied": st["prompts_all_tied"]},
                    console=False)
        say(f"[dpo] step {step}: online pairs regenerated from the policy: {len(new_pairs)} pairs "
            f"({st['prompts_all_tied']} of {len(rows)} prompts tied), labelled by {cfg.online_labeler}")
        if len(new_pairs) < cfg.batch_size:
            raise loop.TrainingError(f"online DPO at step {step}: only {len(new_pairs)} pairs (most prompts tied); "
                                     "raise online_prompts or online_samples")
        return {"pairs": new_pairs, "ref": ref, "start": step, "gen": gen}

    def evaluate(step: int) -> None:
        m: dict[str, float] = heldout_pair_metrics(cfg, model, eval_pairs, ref_eval, ref_model, pad_id, micro)
        if gen_rows and main:
            policy = accelerator.unwrap_model(model)
            rows = gen_rows[: cfg.eval_rows]
            r = evaluation.compare_policy(res.task.name, policy, tokenizer, rows, baseline[: len(rows)],
                                          max_new_tokens=cfg.max_new_tokens, proxy=proxy)
            m.update({"gold/reward": r["gold_reward"], "gold/quality": r["mean_quality"],
                      "gold/in_band": r["frac_in_band"], "gold/length": r["mean_length"],
                      "gold/win_rate": r["win_rate"]})
            if "proxy_reward" in r:
                m["proxy/reward"] = r["proxy_reward"]
            reference = reference_for_eval()
            m["kl"] = evaluation.kl_to_reference(policy, reference, tokenizer, [x["prompt"] for x in rows],
                                                 max_new_tokens=cfg.max_new_tokens, seed=cfg.seed + 7)
            del reference
        metrics.log(step, m, console=False)
        shown = {k: m[k] for k in ("eval/rewards/accuracy", "gold/win_rate", "gold/reward", "proxy/reward", "kl")
                 if k in m}
        say(f"[dpo] step {step} eval: " + ", ".join(f"{k} {v:.3f}" for k, v in shown.items()))
        model.train()

    if start == 0 and cfg.eval_every:
        evaluate(0)
    say(f"[dpo] {len(train_pairs)} training pairs from {source}, batch {cfg.batch_size} (micro {micro}), "
        f"{cfg.max_steps} steps, {cfg.loss_type} loss, beta {cfg.beta}, lr {cfg.lr}, reference {cfg.reference}"
        + (f", online every {cfg.online_every} steps (labeler {cfg.online_labeler})" if cfg.online else ""))
    for step in range(start, cfg.max_steps):
        done = step + 1
        if cfg.online and step > 0 and step % cfg.online_every == 0 and pool["start"] != step:
            pool = refresh_pool(step)
        idx = loop.batch_indices(len(pool["pairs"]), cfg.batch_size, cfg.seed + pool["gen"], step - pool["start"],
                                 accelerator.process_index, accelerator.num_processes)[:per_process]
        micro_idx = loop.chunks(idx, micro)
        micro_batches = [(collate_pairs([pool["pairs"][i] for i in mi], pad_id, cfg.share_prompt),
                          _select(pool["ref"], mi) if pool["ref"] is not None else None, len(mi)) for mi in micro_idx]

        def loss_fn(mb):
            batch, ref, b = mb
            s, n = pair_logps(model, batch)
            if ref is None:
                ref = _ref_from_model(ref_model, batch, b)
            loss, m = pair_loss(cfg, s, n, ref)
            return loss * (b / len(idx)), m  # each micro-batch's share of the batch mean

        try:
            m = loop.optimizer_step(accelerator, model, optimizer, scheduler, micro_batches, loss_fn,
                                    cfg.max_grad_norm, done)
            saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
            if (saving or (cfg.eval_every and done % cfg.eval_every == 0)):
                if not _weights_finite(model):
                    raise loop.TrainingError(f"non-finite weights after step {done}; stopping without saving them")
        except loop.TrainingError as e:
            last = ckpt.latest()
            where = f"last good checkpoint: {last}" if last else "no checkpoint was written yet"
            raise loop.TrainingError(f"{e} ({where})") from None
        if done % cfg.log_every == 0 or done == cfg.max_steps:
            metrics.log(done, {"loss": m["loss"], **{k: v for k, v in m.items() if k not in ("loss",)}})
        if cfg.eval_every and (done % cfg.eval_every == 0 or done == cfg.max_steps):
            evaluate(done)
        if saving:
            extra = None
            if pool["gen"] > 0:  # pairs generated online: saved, so that a resume trains on the same pairs
                extra = {"online_pool": {"pairs": [vars(p) for p in pool["pairs"]], "ref": pool["ref"],
                                         "start": pool["start"], "gen": pool["gen"]}}
            ckpt.save(done, model, optimizer, scheduler, {"step": done}, extra)

    final = run_dir / "final"
    if main:
        policy = accelerator.unwrap_model(model)
        save_model(policy, tokenizer, final)
        say(f"[dpo] saved {final}")
        report: dict[str, Any] = {"model": str(final), "reference": str(sft_dir)}
        note = evaluation.plot_gold_vs_proxy(_read_metrics(run_dir / "metrics.jsonl"),
                                             run_dir / "overoptimization.png", title=f"{res.recipe} DPO")
        say(f"[dpo] over-optimisation plot: {note}")
        if cfg.final_eval_rows and gen_rows:
            rows = gen_rows[: cfg.final_eval_rows]
            base = baseline[: len(rows)]
            sft_m = evaluation.compare_policy(res.task.name, None, tokenizer, rows, base, proxy=proxy, completions=base)
            dpo_m = evaluation.compare_policy(res.task.name, policy, tokenizer, rows, base,
                                              max_new_tokens=cfg.max_new_tokens, proxy=proxy)
            reference = reference_for_eval()
            dpo_m["kl"] = evaluation.kl_to_reference(policy, reference, tokenizer, [r["prompt"] for r in rows],
                                                     max_new_tokens=cfg.max_new_tokens, seed=cfg.seed + 7)
            sft_m["kl"] = 0.0
            del reference
            say(evaluation.format_comparison({"sft": sft_m, "dpo": dpo_m}, res.task.name))
            report.update(sft={k: v for k, v in sft_m.items() if not k.startswith("_")},
                          dpo={k: v for k, v in dpo_m.items() if not k.startswith("_")},
                          samples=[{"prompt": r["prompt"][-200:], "sft": b, "dpo": d}
                                   for r, b, d in zip(rows[:10], baseline, dpo_m["_completions"])])
            counts = (f": {dpo_m['wins']} wins, {dpo_m['ties']} ties, {dpo_m['losses']} losses"
                      if "wins" in dpo_m else "")
            say(f"[dpo] gold win-rate of the DPO model against the SFT model: {dpo_m['win_rate']:.3f} "
                f"({len(rows)} held-out prompts{counts}; ties count half)")
        loop.write_json(run_dir / "eval.json", report)
    accelerator.wait_for_everyone()
    return final


def _read_metrics(path: Path) -> list[dict]:
    return list(loop.iter_jsonl(path)) if Path(path).is_file() else []
