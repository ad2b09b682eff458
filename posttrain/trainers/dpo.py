"""Direct Preference Optimization (Rafailov et al. 2023) on preference pairs; IPO, hinge, SimPO, ORPO, KTO; online mode.

CPU:        posttrain dpo --recipe tiny-summarize    (from nothing: SFT, pairs, reward model, online DPO, eval)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain dpo --recipe tiny-summarize model.path=/path/to/hf-model
            (2 CPU processes: accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain dpo
            --recipe tiny-summarize run.threads=1; tested in tests/posttrain/test_distributed.py)
LoRA:       posttrain dpo --recipe tiny-summarize lora.enabled=true   (the reference: the policy, adapters off)

Implementation details it follows, each with its source and flag (tested in tests/posttrain/trainers/test_dpo.py):
 1. DPO (Rafailov et al. 2023, eq. 7; `loss_type=sigmoid`, `beta`): -log sigmoid(beta h), h the chosen minus
    the rejected log-ratio to the reference (`losses.dpo_loss`); log-probs summed over completion tokens + eos.
 2. Conservative DPO label smoothing (Mitchell 2023; TRL's label_smoothing; `label_smoothing`, sigmoid only).
 3. IPO (Azar et al. 2023, eq. 17; `loss_type=ipo`): (h - 1/(2 beta))^2, on length-averaged log-probs.
 4. Hinge / SLiC-HF (Zhao et al. 2023, in TRL's form; `loss_type=hinge`): relu(1 - beta h).
 5. RPO (Pang et al. 2024; TRL's rpo_alpha; `chosen_nll_weight`): + weight x per-token NLL of the chosen side.
 6. Prefix sharing (`share_prompt`): a pair is ONE row, prompt + chosen + rejected, under a 4D mask in which the
    rejected tokens see the prompt and themselves (`data.collate_shared_prompt`); false: chosen rows, then
    rejected rows, in one forward (TRL's concatenated_forward). The log-probs are the same either way.
 7. Precomputed vs live reference (`reference`): "precomputed" (TRL's precompute_ref_log_probs) keeps only the
    SFT model's log-prob sums of the pairs, taken before the first update; "live" a frozen copy (same numbers).
    Either is taken in the run's precision (under run.mixed_precision=bf16 the same bf16 autocast as the policy's
    log-probs, as TRL's reference: the implicit rewards start at 0 up to batching, not at the bf16 - fp32 gap).
 8. Online / iterative DPO (Guo et al. 2024, online AI feedback; `online`, `online_every`, `online_*`): every
    online_every steps, pairs sampled from the policy, labelled as the prefs stage does (`online_labeler`: gold
    or reward model), replace the training pairs; `save_rollouts_every` saves them (`posttrain rollouts`).
 9. Evaluation (`eval_every`, `eval_pairs`, `eval_rows`, `proxy_rm`, `final_eval_rows`): held-out pair loss and
    implicit-reward accuracy; for a gold task `evaluation.policy_eval` (gold metrics, win-rate vs SFT, proxy RM
    reward, KL to the reference), the over-optimisation plot of Gao et al. 2022, `evaluation.compare_with_sft`.
10. SimPO (Meng et al. 2024, eq. 6; `loss_type=simpo`, `beta`, `simpo_gamma`): -log sigmoid(beta (l_c - l_r) - gamma)
    with l the per-token mean log-prob: reference-free (`losses.simpo_loss`), so no reference log-probs are taken.
11. ORPO (Hong et al. 2024, eq. 6-7; `loss_type=orpo`, `beta` as ORPO's lambda, as TRL names it): the chosen
    side's per-token NLL + lambda x -log sigmoid(log-odds ratio) (`losses.orpo_loss`): one stage, reference-free.
12. KTO (Ethayarajh et al. 2024, eq. 7-8; `loss_type=kto`, `beta`, `desirable_weight`, `undesirable_weight`):
    unpaired completions (TRL's format: prompt, completion, label; pairs unpaired as TRL does), each pushed above
    or below the reference point z0, a KL(pi || pi_ref) estimate from completions under ANOTHER row's prompt
    (`losses.kto_loss`; rows travel as (completion, KL partner) pairs: `preferences.check_unpaired`).

Deviations and limits:
- IPO on length-averaged log-probs (as TRL); Azar et al. define it on sequence log-likelihoods.
- KTO's z0 is the mean over each micro-batch's KL partners (TRL: the device batch, gathered across processes);
  each row's KL partner is fixed (the next row with another prompt), not redrawn per batch.
- Online DPO labels a batch of pairs every online_every steps; Guo et al. label fresh pairs at every step.
- reference=precomputed: the KL eval and online pairs need the reference on NEW sequences: the SFT model is
  loaded from disk for that moment (LoRA: the policy with its adapters off, no copy).
- Bad rows (`on_bad_rows`: chosen == rejected, an empty side, too long): "error" stops before anything runs,
  naming the file and row; "skip" drops them with a count per reason.
- A non-finite loss, gradient or weights stops the run naming the step and the last good checkpoint (intact);
  resume=true continues exactly (data order from (seed, step); the online pool is in the checkpoint).
- Several processes: batch_size is global, process r takes positions r, r + W, ... of each batch; the gold /
  proxy / KL evaluation, the baseline, metrics, final/ and eval.json are the main process's.
"""
from __future__ import annotations

import contextlib
import random
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal

import torch

from posttrain import evaluation, loop, models, preferences, scoring, tasks
from posttrain.config import ConfigError, Resolved
from posttrain.losses import dpo_loss, kto_loss, orpo_loss, simpo_loss
from posttrain.data import TokenizedPair, collate_pairs
from posttrain.preferences import by_side, pair_groups, pair_logps, reference_logps

if TYPE_CHECKING:  # the annotations of the run object only
    from accelerate import Accelerator
    from transformers import PreTrainedTokenizerBase


@dataclass
class DPOConfig(loop.TrainingConfig):
    train_file: str | None = None
    """Preference file (JSONL/JSON/Parquet: prompt, chosen, rejected); empty: the prefs stage output (sampled)."""
    eval_file: str | None = None
    """Held-out preference file; empty: the prefs stage's eval pairs (or 5% of train_file)."""
    beta: float = 0.1
    """KL strength: implicit reward = beta * (log pi - log pi_ref)."""
    loss_type: Literal["sigmoid", "ipo", "hinge", "simpo", "orpo", "kto"] = "sigmoid"
    """sigmoid: DPO; ipo: IPO (length-averaged); hinge: SLiC-HF; simpo: SimPO and orpo: ORPO (reference-free; beta
    is SimPO's beta, paper 2-10, and ORPO's lambda, paper 0.1-0.2); kto: KTO on unpaired labelled completions."""
    desirable_weight: float = 1.0
    """KTO's lambda_D, the weight of desirable rows (the paper keeps lambda_D n_D / (lambda_U n_U) in [1, 4/3])."""
    undesirable_weight: float = 1.0
    """KTO's lambda_U, the weight of undesirable rows."""
    simpo_gamma: float = 0.5
    """SimPO's target reward margin gamma (>= 0; the paper tunes 0.3-1.6)."""
    label_smoothing: float = 0.0
    """Conservative DPO: assumed probability that a label is flipped (sigmoid only, <= 0.5)."""
    chosen_nll_weight: float = 0.0
    """RPO (Pang et al. 2024): add this weight times the per-token NLL of the chosen completions (TRL's rpo_alpha)."""
    share_prompt: bool = True
    """Prefix sharing: one row per pair (prompt, chosen, rejected; rejected masked off chosen), prompt computed once."""
    reference: Literal["precomputed", "live"] = "precomputed"
    """precomputed: reference log-probs once before training, no reference model in memory; live: a frozen copy."""
    batch_size: int = 32
    """Pairs per optimizer step (global, across processes)."""
    eval_rows: int = 100
    """Held-out prompts for the periodic gold / proxy / KL evaluation."""
    eval_pairs: int = 200
    """Held-out pairs for the periodic implicit-reward accuracy."""
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
    save_rollouts_every: int = 0
    """Online DPO: save the regenerations' samples every this many steps (0: never; `posttrain rollouts`)."""
    on_bad_rows: Literal["error", "skip"] = "error"
    """Bad pairs (chosen == rejected, empty side, too long): stop with the file and row, or skip with a count."""
    # loop.TrainingConfig's fields (one docstring each, there) whose default is this trainer's own:
    max_steps: int = 200
    schedule: Literal["cosine", "linear", "constant"] = "linear"
    log_every: int = 10
    eval_every: int = 50
    save_every: int = 100
    warmup_steps: int = 10


def check_config(cfg: DPOConfig) -> None:
    """Inconsistent settings are a ConfigError before anything runs."""
    if cfg.online and cfg.online_every < 1:
        raise ConfigError(f"dpo.online_every must be >= 1, got {cfg.online_every}")
    if cfg.save_rollouts_every and (not cfg.online or cfg.save_rollouts_every % cfg.online_every):
        raise ConfigError(f"dpo.save_rollouts_every={cfg.save_rollouts_every} saves the samples of online DPO's "
                          f"regenerations: it needs online=true and a multiple of online_every={cfg.online_every}")
    if cfg.label_smoothing and cfg.loss_type != "sigmoid":
        raise ConfigError(f"dpo.label_smoothing applies to loss_type=sigmoid only (got loss_type={cfg.loss_type})")
    if not 0.0 <= cfg.label_smoothing <= 0.5 or cfg.beta <= 0:
        raise ConfigError("dpo.beta must be > 0 and dpo.label_smoothing in [0, 0.5]")
    if cfg.simpo_gamma < 0:
        raise ConfigError(f"dpo.simpo_gamma must be >= 0, got {cfg.simpo_gamma}")
    if cfg.loss_type == "kto" and (cfg.online or cfg.chosen_nll_weight):
        raise ConfigError("dpo.loss_type=kto trains on fixed labelled completions: online=true and chosen_nll_weight "
                          "(RPO) are not supported with it")
    if cfg.desirable_weight < 0 or cfg.undesirable_weight < 0:
        raise ConfigError(f"dpo.desirable_weight and dpo.undesirable_weight must be >= 0, got {cfg.desirable_weight}, "
                          f"{cfg.undesirable_weight}")


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """Train the SFT model with DPO on preference pairs; returns the final model directory."""
    cfg: DPOConfig = res.stage_cfg
    check_config(cfg)
    run = setup(res, cfg, ensure)  # pairs (checked first), the model, the reference, optimizer, resume, baseline
    pool = run.pool
    for step in range(run.start, cfg.max_steps):
        done = step + 1
        # ---- online pairs (detail 8): every online_every steps, fresh pairs from the policy replace the pool
        if cfg.online and step > 0 and step % cfg.online_every == 0 and pool.start != step:
            pool = refresh_pool(step, cfg, run.policy, run.tokenizer, res.model.max_length, run.data.online_rows,
                                online_labeler(run), run.ref, run.budget, run.metrics, run.say,
                                run.run_dir if run.main else None)
        # ---- batch: this process's share of the step's pairs (indices into the pool), in micro-batches
        idx = loop.batch_indices(len(pool.pairs), cfg.batch_size, pool.order_seed(cfg.seed), step - pool.start,
                                 run.accelerator.process_index, run.accelerator.num_processes)[:run.per_process]
        # ---- update: one forward over chosen and rejected per micro-batch, accumulated into one optimizer step
        saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
        with loop.naming_checkpoint(run.ckpt):
            m = loop.optimizer_step(run.accelerator, run.model, run.optimizer, run.scheduler,
                                    micro_groups(cfg, pool, idx, run.budget),
                                    lambda mi: micro_batch_loss(cfg, run.model, run.ref.live, pool, mi,
                                                                run.tokenizer.pad_token_id, len(idx),
                                                                run.ref.precision),
                                    cfg.max_grad_norm, done)
            if saving or (cfg.eval_every and done % cfg.eval_every == 0):
                loop.check_weights(done, run.model)
        # ---- log
        if done % cfg.log_every == 0 or done == cfg.max_steps:
            run.metrics.log(done, {"loss": m["loss"], **m})  # the loss first on the console line
        # ---- eval
        if cfg.eval_every and (done % cfg.eval_every == 0 or done == cfg.max_steps):
            evaluate(done, run)
        # ---- checkpoint (with an online pool, so that a resume trains on the same pairs)
        if saving:
            run.ckpt.save(done, run.model, run.optimizer, run.scheduler, {"step": done},
                          {"online_pool": asdict(pool)} if pool.gen > 0 else None)
    return finish(run)


# ----------------------------------------------------------------------------- setup and the end of a run
@dataclass(kw_only=True)
class DPORun:
    """What a run holds between steps (`setup`)."""

    res: Resolved
    cfg: DPOConfig
    accelerator: Accelerator
    say: Callable[[str], None]  # prints on the main process
    run_dir: Path
    main: bool
    sft_dir: Path
    rm_dir: Path | None  # the proxy reward model (and online_labeler=rm's labeller)
    data: PairData
    tokenizer: PreTrainedTokenizerBase
    model: torch.nn.Module  # as accelerate prepared it
    policy: torch.nn.Module  # the model inside the DDP / FSDP wrapper: generation, saving
    ref: Reference
    budget: int  # padded tokens per micro-batch (memory)
    per_process: int  # pairs per process of a batch
    baseline: list[str]  # the SFT model's completions of the gold rows (main process)
    proxy: scoring.RewardModelScorer | None  # the proxy reward model's scorer (main process), or None
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    ckpt: loop.Checkpointer
    metrics: loop.MetricsLog
    pool: Pool  # the pairs of the first step: the offline pairs or a resumed online pool
    start: int  # the first step (resume)


def setup(res: Resolved, cfg: DPOConfig, ensure) -> DPORun:
    """The pairs (a bad row stops the run before the run directory changes), the proxy reward model, the SFT model
    as reference (precomputed log-probs, a live copy, or none) and baseline completions, then, unchanged, as the
    policy; optimizer, resumed state and pool; the step-0 evaluation."""
    data, sft_dir, tokenizer = load_pairs(res, ensure, cfg)
    rm_dir = resolve_proxy_rm(res, ensure, cfg.proxy_rm, cfg.online and cfg.online_labeler == "rm")
    accelerator, say = loop.start_run(res, cfg.seed, cfg.resume)
    main, dev, pad_id = accelerator.is_main_process, accelerator.device, tokenizer.pad_token_id
    micro, per_process = cfg.micro_batch_size or cfg.batch_size, max(1, cfg.batch_size // accelerator.num_processes)

    # The SFT model: the reference (and the baseline completions), then, unchanged, the policy.
    model = models.maybe_lora(res, models.load_model(sft_dir, res.model.dtype, device=dev), say)  # LoRA: adapters 0
    budget = models.token_budget(res.run.micro_batch_tokens, model)  # padded tokens per micro-batch (memory)
    ref = Reference(res, sft_dir, dev, precision=accelerator.autocast)  # the run's precision, as the policy's
    if cfg.loss_type in REFERENCE_FREE:  # SimPO, ORPO: no reference log-probs at all (the KL eval loads the SFT model)
        ref_train = None
    elif cfg.reference == "precomputed":
        ref_train, ref.heldout = precompute_reference(cfg, model, data, pad_id, budget, say, ref.precision)
    else:
        ref_train, ref.live = None, models.load_reference(res, model, sft_dir, dev)
    baseline = evaluation.complete(model, tokenizer, [r["prompt"] for r in data.gold_rows],
                                   max_new_tokens=cfg.max_new_tokens) if (data.gold_rows and main) else []
    proxy = scoring.RewardModelScorer(rm_dir, device=dev) if (rm_dir is not None and main) else None
    if rm_dir is not None:
        say(f"[dpo] proxy reward model: {rm_dir}")
    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps, cfg.schedule, cfg.min_lr_ratio)
    model, optimizer = accelerator.prepare(model, optimizer)
    ckpt = loop.Checkpointer(res.stage_dir(), cfg.keep_checkpoints, accelerator)
    metrics = loop.open_metrics(res, cfg.max_steps, main, "[dpo] ")
    state = loop.resume_run(ckpt, metrics, model, optimizer, scheduler, resume=cfg.resume, say=say, tag="dpo")
    start, saved = state["step"], state["extra"].get("online_pool")  # an online pool (the offline one: rebuilt)
    pool = Pool(**{**saved, "pairs": [TokenizedPair(**p) for p in saved["pairs"]]}) if saved else \
        Pool(data.train, ref_train, labels=data.train_labels)
    policy = accelerator.unwrap_model(model)  # the model inside the DDP / FSDP wrapper: generation, saving
    run = DPORun(res=res, cfg=cfg, accelerator=accelerator, say=say, run_dir=res.stage_dir(), main=main,
                 sft_dir=sft_dir, rm_dir=rm_dir, data=data, tokenizer=tokenizer, model=model, policy=policy, ref=ref,
                 budget=budget, per_process=per_process, baseline=baseline, proxy=proxy, optimizer=optimizer,
                 scheduler=scheduler, ckpt=ckpt, metrics=metrics, pool=pool, start=start)
    if start == 0 and cfg.eval_every:
        evaluate(0, run)
    what = "rows (each with its KL partner)" if cfg.loss_type == "kto" else "pairs"
    say(f"[dpo] {len(data.train)} training {what} from {data.source}, batch {cfg.batch_size} (micro {micro} pairs, "
        f"<= {budget} tokens), "
        f"{cfg.max_steps} steps, {cfg.loss_type} loss, beta {cfg.beta}, lr {cfg.lr}, "
        + ("no reference (a reference-free loss)" if cfg.loss_type in REFERENCE_FREE else f"reference {cfg.reference}")
        + (f", online every {cfg.online_every} steps (labeler {cfg.online_labeler})" if cfg.online else ""))
    return run


def online_labeler(run: DPORun):
    """Online DPO's labeller: the gold preference, or the reward model (the proxy's scorer when it is loaded)."""
    if run.cfg.online_labeler == "gold":
        return preferences.gold_labeler(run.res.task.name)
    return preferences.scorer_labeler(run.proxy if run.proxy is not None else scoring.RewardModelScorer(run.rm_dir))


def finish(run: DPORun) -> Path:
    """final/ (every process gathers a sharded model; the main process saves), the over-optimisation plot, the
    comparison with the SFT model and eval.json; returns final/."""
    cfg, res, run_dir, policy = run.cfg, run.res, run.run_dir, run.policy
    final = run_dir / "final"
    whole = loop.full_state_dict(run.accelerator, run.model)  # every process: gathers a sharded model (FSDP, ZeRO-3)
    if run.main:
        models.save_model(policy, run.tokenizer, final, state_dict=whole)
        run.say(f"[dpo] saved {final}")
        report: dict[str, Any] = {"model": str(final), "reference": str(run.sft_dir)}
        path = run.metrics.path
        note = evaluation.plot_gold_vs_proxy(list(loop.iter_jsonl(path)) if path.is_file() else [],
                                             run_dir / "overoptimization.png", title=f"{res.recipe} DPO")
        run.say(f"[dpo] over-optimisation plot: {note}")
        if cfg.final_eval_rows and run.baseline:
            report.update(evaluation.compare_with_sft(
                "dpo", res.task.name, policy, run.ref.model_for(policy), run.tokenizer,
                run.data.gold_rows[: cfg.final_eval_rows], run.baseline, max_new_tokens=cfg.max_new_tokens,
                proxy=run.proxy, seed=loop.stream_seed(cfg.seed, "eval/sample"), say=run.say))
        loop.write_json(run_dir / "eval.json", report)
        run.metrics.close(report)
    run.metrics.close()
    run.accelerator.wait_for_everyone()
    return final


# ----------------------------------------------------------------------------- the loss of pairs
REFERENCE_FREE = ("simpo", "orpo")


def pair_loss(cfg: DPOConfig, policy_logps: torch.Tensor, policy_tokens: torch.Tensor,
              ref: dict[str, torch.Tensor] | None, labels: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, dict[str, float]]:
    """The preference loss of one micro-batch: policy (2B,) sums + token counts, reference {chosen, rejected,
    *_tokens} (B,) (None for the reference-free losses). KTO (`labels`: (B,) bool, desirable rows): `kto_rows_loss`."""
    if cfg.loss_type == "kto":  # detail 12
        return kto_rows_loss(cfg, policy_logps, ref, labels)
    B = policy_logps.shape[0] // 2
    pc, pr = policy_logps[:B], policy_logps[B:]  # (B,), (B,)
    if cfg.loss_type == "simpo":  # detail 10
        loss, metrics = simpo_loss(pc, pr, policy_tokens[:B], policy_tokens[B:], beta=cfg.beta, gamma=cfg.simpo_gamma)
    elif cfg.loss_type == "orpo":  # detail 11
        loss, metrics = orpo_loss(pc, pr, policy_tokens[:B], policy_tokens[B:], lam=cfg.beta)
    else:
        rc, rr = ref["chosen"].to(pc.device), ref["rejected"].to(pc.device)  # (B,), (B,)
        if cfg.loss_type == "ipo":  # detail 3: length-averaged log-probs for policy and reference (TRL)
            pc, pr = pc / policy_tokens[:B], pr / policy_tokens[B:]
            rc, rr = rc / ref["chosen_tokens"].to(pc.device), rr / ref["rejected_tokens"].to(pc.device)
        loss, metrics = dpo_loss(pc, pr, rc, rr, beta=cfg.beta, loss_type=cfg.loss_type,
                                 label_smoothing=cfg.label_smoothing)
    if cfg.chosen_nll_weight:  # detail 5 (RPO)
        nll = -(policy_logps[:B] / policy_tokens[:B].clamp(min=1)).mean()  # per-token NLL of chosen, mean over pairs
        loss = loss + cfg.chosen_nll_weight * nll
        metrics["nll/chosen"] = float(nll.detach())
    return loss, metrics


def kto_rows_loss(cfg: DPOConfig, policy_logps: torch.Tensor, ref: dict[str, torch.Tensor],
                  desirable: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """Detail 12 on one micro-batch of B rows. A KTO row travels as a pair, (its completion, its KL partner), so
    that prefix sharing and the precomputed reference apply: the pair's sides hold the completion (the first B
    policy sums, ref["chosen"]) and the KL partner (the last B, ref["rejected"]). `desirable`: (B,) bool labels."""
    B = policy_logps.shape[0] // 2
    completion, kl_partner = policy_logps[:B], policy_logps[B:]  # (B,), (B,)
    dev = completion.device
    ref_completion, ref_kl_partner = ref["chosen"].to(dev), ref["rejected"].to(dev)  # (B,), (B,)
    return kto_loss(completion, ref_completion, desirable.to(dev), kl_partner, ref_kl_partner, beta=cfg.beta,
                    desirable_weight=cfg.desirable_weight, undesirable_weight=cfg.undesirable_weight)


@dataclass
class Pool:
    """Pairs and their precomputed reference log-probs (None: reference=live); online pools replace the offline one."""
    pairs: list[TokenizedPair]
    ref: dict[str, torch.Tensor] | None
    start: int = 0  # the step it was built at: its batches are loop.batch_indices(..., order_seed, step - start)
    gen: int = 0  # the regeneration index; 0: the offline pairs
    labels: list[bool] | None = None  # KTO: per row, desirable or not (its pairs are (completion, KL partner))

    def order_seed(self, seed: int) -> int:
        """The seed of the pool's batch order: the run's own for the offline pairs (the order the precomputed
        reference covers), a stream per regeneration for online pools."""
        return seed if self.gen == 0 else loop.stream_seed(seed, "dpo/online-batch", self.gen)


def micro_batch_loss(cfg: DPOConfig, model, ref_model, pool: Pool, idx: list[int], pad_id: int,
                     batch_pairs: int, ref_precision: Callable[[], Any] = contextlib.nullcontext
                     ) -> tuple[torch.Tensor, dict[str, float]]:
    """`pair_loss` of pool.pairs[idx] (reference: the pool's log-probs or `ref_model`, the latter's forward under
    `ref_precision`, the run's autocast), times len(idx) / batch_pairs."""
    batch = collate_pairs([pool.pairs[i] for i in idx], pad_id, cfg.share_prompt)
    s, n = pair_logps(model, batch)
    with torch.no_grad(), ref_precision():  # the reference: precomputed in the pool, the live model's, or none
        ref = None if cfg.loss_type in REFERENCE_FREE else \
            {k: v[torch.as_tensor(idx, dtype=torch.long)] for k, v in pool.ref.items()} if pool.ref is not None \
            else by_side(*pair_logps(ref_model, batch), len(idx))
    labels = torch.tensor([pool.labels[i] for i in idx]) if pool.labels is not None else None
    loss, m = pair_loss(cfg, s, n, ref, labels)
    return loss * (len(idx) / batch_pairs), m


# ----------------------------------------------------------------------------- data, reference, online pairs
@dataclass
class PairData:
    """What DPO trains and evaluates on, read and checked before the run directory changes."""
    train: list[TokenizedPair]
    heldout: list[TokenizedPair]  # the first eval_pairs held-out pairs
    source: str
    gold_rows: list[dict]  # held-out prompts with task meta (gold / proxy / KL eval); [] without a gold preference
    online_rows: list[dict]  # the training prompts of online DPO
    train_labels: list[bool] | None = None  # KTO: the rows' labels (train / heldout are (completion, KL partner))
    heldout_labels: list[bool] | None = None


def load_pairs(res: Resolved, ensure, cfg: DPOConfig) -> tuple[PairData, Path, Any]:
    """(data, SFT model dir, tokenizer). on_bad_rows=error: a bad row stops before SFT may have to run."""
    train_rows, eval_rows, source, eval_source = preferences.training_pairs(ensure, cfg.train_file, cfg.eval_file,
                                                                           seed=cfg.seed,
                                                                           columns=res.task.columns.mapping())
    kto = cfg.loss_type == "kto"
    if cfg.on_bad_rows == "error" and not kto:  # fail fast on what needs no tokenizer
        preferences.check_pairs(train_rows, source, "error")
        preferences.check_pairs(eval_rows[: cfg.eval_pairs], eval_source, "error")
    has_gold = tasks.has_gold_preference(tasks.get_task(res.task.name))
    # gold evaluation needs each held-out prompt's task meta (a task.eval_file may not carry it)
    gold_rows = [r for r in tasks.load_split(res.task, "eval") if r.get("meta")] if has_gold else []
    if cfg.online and cfg.online_labeler == "gold" and not has_gold:
        raise ConfigError(f"dpo.online_labeler=gold needs a task with a gold preference; {res.task.name!r} has none")
    online_rows = tasks.load_split(res.task, "train") if cfg.online else []
    sft_dir = ensure("sft")
    tokenizer = models.load_tokenizer(sft_dir, res.model)
    checked, labels = [], []
    for rows, src, what in ((train_rows, source, ""), (eval_rows[: cfg.eval_pairs], eval_source, "held-out pairs: ")):
        if kto:  # detail 12: unpaired rows, each with its KL partner (a few held-out rows: their pairs, unpaired)
            pairs, lab, bad = preferences.check_unpaired(rows, src, cfg.on_bad_rows, tokenizer, res.model.max_length) \
                if rows else ([], [], preferences.BadRows(src))
            labels.append(lab)
        else:
            _, pairs, bad = preferences.check_pairs(rows, src, cfg.on_bad_rows, tokenizer, res.model.max_length)
        if bad.count:
            print(f"[dpo] {what}{bad.summary()}")  # on every process
        checked.append(pairs)
    if len(checked[0]) < cfg.batch_size:
        raise loop.TrainingError(f"only {len(checked[0])} usable preference {'rows' if kto else 'pairs'} in {source}, "
                                 f"fewer than batch_size={cfg.batch_size}")
    gold_rows = gold_rows[: max(cfg.eval_rows, cfg.final_eval_rows)]
    return PairData(checked[0], checked[1], source, gold_rows, online_rows, *(labels or [None, None])), sft_dir, \
        tokenizer


def resolve_proxy_rm(res: Resolved, ensure, spec: str, need: bool) -> Path | None:
    """The reward-model directory for proxy scores (see DPOConfig.proxy_rm); `need`: online_labeler=rm."""
    if spec not in ("auto", "none", "train"):
        if not models.is_model_dir(spec):
            raise ConfigError(f"proxy_rm {spec!r} is not a reward-model directory; give auto, none, train or a path")
        return Path(spec)
    if spec == "train" or need:
        return ensure("rm")
    final = res.stage_dir("rm") / "final"
    return final if spec == "auto" and models.is_model_dir(final) else None


@dataclass
class Reference:
    """DPO's reference, the SFT model (detail 7): a `live` frozen copy, or its precomputed held-out log-probs."""
    res: Resolved
    sft_dir: Path
    device: Any
    live: Any = None  # reference=live: the frozen copy (LoRA: the policy with its adapters off)
    heldout: dict[str, torch.Tensor] | None = None  # reference=precomputed: (N,) log-probs of the held-out pairs
    precision: Callable[[], Any] = contextlib.nullcontext  # the run's autocast, every reference log-prob under it

    def model_for(self, policy):
        """For NEW sequences (KL, online pairs): the live copy, the policy with LoRA off, or the SFT model for now."""
        if self.live is not None:
            return self.live
        return models.load_reference(self.res, policy, self.sft_dir, self.device)


def precompute_reference(cfg: DPOConfig, model, data: PairData, pad_id: int, budget: int, say,
                         precision: Callable[[], Any] = contextlib.nullcontext) -> tuple[dict, dict]:
    """Reference log-probs of the held-out pairs and of the training pairs the run draws (the others NaN, unused),
    under `precision` (the run's autocast: the policy's log-probs are taken in the same precision).

    The training pairs go step by step: each step's pairs not drawn before, in micro-batches of their own. A
    pair's numbers then depend on the seed and the data, not on max_steps (which pairs share a micro-batch moves
    the last bits of a forward), so a run resumed with a larger max_steps gets the uninterrupted run's numbers."""
    t0, micro = time.time(), cfg.micro_batch_size or cfg.batch_size
    offline_steps = min(cfg.max_steps, cfg.online_every) if cfg.online else cfg.max_steps  # online: then new pairs
    chunks, seen = [], set()
    for s in range(offline_steps):
        new = sorted({i for i in loop.batch_indices(len(data.train), cfg.batch_size, cfg.seed, s) if i not in seen})
        seen.update(new)
        chunks += [new] if new else []
    with precision():
        parts = [reference_logps(model, [data.train[i] for i in c], pad_id, micro, cfg.share_prompt, budget)
                 for c in chunks]
        ref_heldout = reference_logps(model, data.heldout, pad_id, micro, cfg.share_prompt, budget)
    used = torch.tensor([i for c in chunks for i in c], dtype=torch.long)
    ref_train = {k: torch.full((len(data.train),), float("nan")).index_copy(
        0, used, torch.cat([p[k] for p in parts]) if parts else torch.zeros(0))
        for k in ("chosen", "rejected", "chosen_tokens", "rejected_tokens")}
    say(f"[dpo] reference log-probs of {len(used)} training and {len(data.heldout)} held-out pairs "
        f"precomputed in {time.time() - t0:.1f}s; no reference model is kept in memory")
    return ref_train, ref_heldout


def refresh_pool(step: int, cfg: DPOConfig, policy, tokenizer, max_length: int, rows: list[dict], labeler,
                 ref: Reference, budget: int, metrics: loop.MetricsLog, say, save_to: Path | None = None) -> Pool:
    """Online DPO (detail 8): a pool of fresh pairs from `policy` on sampled training `rows`, labelled by `labeler`;
    the samples saved under `save_to` (the run directory, on the main process) at save_rollouts_every."""
    from posttrain.rollout.records import save_step_rollouts

    gen = step // cfg.online_every
    idx = random.Random(loop.stream_seed(cfg.seed, "dpo/online-prompts", gen)).sample(
        range(len(rows)), min(cfg.online_prompts, len(rows)))
    samples = [] if save_to is not None and cfg.save_rollouts_every and step % cfg.save_rollouts_every == 0 else None
    new_rows, st = preferences.sample_pairs(
        policy, tokenizer, [rows[i] for i in idx], labeler, prompt_keys=idx, samples_per_prompt=cfg.online_samples,
        pairs_per_prompt=cfg.online_pairs_per_prompt, temperature=cfg.online_temperature,
        max_new_tokens=cfg.max_new_tokens, seed=loop.stream_seed(cfg.seed, "dpo/online-sample", gen),
        strategy=f"online-{cfg.online_labeler}",
        rollouts_out=samples)
    if samples:  # rollout inspection: every sample with its label and its role in the pairs
        metrics.log_table("rollouts", save_step_rollouts(samples, save_to, step), step)
    _, pairs, _ = preferences.check_pairs([{**r, "_row": i + 1} for i, r in enumerate(new_rows)],
                                          f"online pairs (step {step})", "skip", tokenizer, max_length)
    pair_ref = None
    if cfg.reference == "precomputed" and cfg.loss_type not in REFERENCE_FREE:
        with ref.precision():
            pair_ref = reference_logps(ref.model_for(policy), pairs, tokenizer.pad_token_id, cfg.micro_batch_size or
                                       cfg.batch_size, cfg.share_prompt, budget)
    metrics.log(step, {"online/pairs": len(pairs), "online/prompts_all_tied": st["prompts_all_tied"]}, console=False)
    say(f"[dpo] step {step}: online pairs regenerated from the policy: {len(pairs)} pairs "
        f"({st['prompts_all_tied']} of {len(idx)} prompts tied), labelled by {cfg.online_labeler}")
    if len(pairs) < cfg.batch_size:
        raise loop.TrainingError(f"online DPO at step {step}: only {len(pairs)} pairs (most prompts tied); "
                                 "raise online_prompts or online_samples")
    return Pool(pairs, pair_ref, step, gen)


def micro_groups(cfg: DPOConfig, pool: Pool, idx: list[int], budget: int) -> list[list[int]]:
    """Pool indices `idx` in micro-batches of at most micro_batch_size pairs and `budget` padded tokens."""
    groups = pair_groups([pool.pairs[i] for i in idx], cfg.micro_batch_size or cfg.batch_size, budget, cfg.share_prompt)
    return [[idx[j] for j in g] for g in groups]


def evaluate(step: int, run: DPORun) -> None:
    """Held-out pair metrics (every process); with the SFT baseline (main process), `evaluation.policy_eval`."""
    cfg, model, policy, data, ref = run.cfg, run.model, run.policy, run.data, run.ref
    heldout, sums = Pool(data.heldout, ref.heldout, labels=data.heldout_labels), {}
    if heldout.pairs:
        model.eval()
    with torch.no_grad():
        for idx in micro_groups(cfg, heldout, list(range(len(heldout.pairs))), run.budget):
            loss, m = micro_batch_loss(cfg, model, ref.live, heldout, idx, run.tokenizer.pad_token_id, len(idx),
                                       ref.precision)
            for k, v in {**m, "loss": float(loss)}.items():
                sums[k] = sums.get(k, 0.0) + v * len(idx)
    m = {f"eval/{k}": v / len(heldout.pairs) for k, v in sums.items()}
    if run.baseline:
        m.update(evaluation.policy_eval(run.res.task.name, policy, ref.model_for(policy), run.tokenizer,
                                        data.gold_rows[: cfg.eval_rows], run.baseline,
                                        max_new_tokens=cfg.max_new_tokens, proxy=run.proxy,
                                        seed=loop.stream_seed(cfg.seed, "eval/sample")))
    run.metrics.log(step, m, console=False)
    shown = {k: m[k] for k in ("eval/rewards/accuracy", "gold/win_rate", "gold/reward", "proxy/reward", "kl") if k in m}
    run.say(f"[dpo] step {step} eval: " + ", ".join(f"{k} {v:.3f}" for k, v in shown.items()))
    model.train()
