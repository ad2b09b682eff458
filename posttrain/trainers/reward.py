"""Reward model: a scalar head on the SFT model trained with the Bradley-Terry loss on preference pairs.

CPU:        posttrain rm --recipe tiny-summarize          (~1 min on 2 cores once SFT and prefs exist)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain rm --recipe tiny-summarize model.path=/path/to/hf-model

Reads top to bottom: load pairs (the prefs stage output, or rm.train_file) and check them; load
the SFT model as `AutoModelForSequenceClassification(num_labels=1)` (the transformer is the SFT
model's, the one-output `score` head is new, seeded); loop { batch of pairs -> one forward over
chosen and rejected -> bradley_terry_loss -> optimizer step -> log -> held-out pair accuracy ->
checkpoint }; save final/ as a HF directory that loads back with
`AutoModelForSequenceClassification.from_pretrained` and scores the same.

Details:
- Loss: `posttrain.losses.bradley_terry_loss` (Christiano et al. 2017; Ouyang et al. 2022 eq. 1),
  mean of -log sigmoid(r_chosen - r_rejected). Metrics: pair accuracy (r_chosen > r_rejected) and
  margin (mean r_chosen - r_rejected), on training batches and held-out pairs.
- Input: prompt (with the tokenizer's special tokens) + completion + eos, left-padded; the reward
  is the head's output at the last token (`posttrain.scoring.reward_forward`, which also documents
  why that equals HF's own pooling). When the tokenizer pads with eos, the eos is left off so
  both poolings still agree. `posttrain.scoring.RewardModelScorer` builds inputs the same way.
- Chosen and rejected go through the model in one forward: on the lean path (a plain Llama-family model, no LoRA)
  one row per pair, prompt + chosen + rejected under DPO's prefix-sharing mask, so the prompt runs once
  (`scoring.pair_rewards`; the same rewards within fp32 rounding); otherwise two rows per pair along the batch.
- Unlike TRL's RewardTrainer we do not truncate long rows: pairs longer than model.max_length
  are bad rows (`on_bad_rows`: stop naming the row, or skip with a count), as in DPO.
- Non-finite loss: `loop.optimizer_step` stops before the update; weights are checked before
  each checkpoint; the last good checkpoint stays intact (resume=true continues from it).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal

import torch

from posttrain import loop
from posttrain.config import Resolved
from posttrain.losses import bradley_terry_loss
from posttrain.data import TokenizedPair
from posttrain.preferences import pair_groups
from posttrain.scoring import pair_rewards, rm_appends_eos

if TYPE_CHECKING:  # the annotations of the run object only
    from accelerate import Accelerator
    from transformers import PreTrainedTokenizerBase


@dataclass
class RMConfig(loop.TrainingConfig):
    train_file: str | None = None
    """Preference file (JSONL/JSON/Parquet: prompt, chosen, rejected); empty: the prefs stage output (sampled)."""
    eval_file: str | None = None
    """Held-out preference file; empty: the prefs stage's eval pairs (or 5% of train_file)."""
    batch_size: int = 32
    """Pairs per optimizer step (global, across processes)."""
    eval_pairs: int = 500
    """Held-out pairs evaluated."""
    on_bad_rows: Literal["error", "skip"] = "error"
    """Bad pairs (chosen == rejected, empty side, too long): stop with the file and row, or skip with a count."""
    # loop.TrainingConfig's fields (one docstring each, there) whose default is this trainer's own:
    lr: float = 3e-4
    max_steps: int = 150
    schedule: Literal["cosine", "linear", "constant"] = "cosine"
    log_every: int = 10
    eval_every: int = 50
    warmup_steps: int = 10
    min_lr_ratio: float = 0.1


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """Train a reward model on preference pairs; returns the final HF directory."""
    cfg: RMConfig = res.stage_cfg
    run = setup(res, cfg, ensure)  # data first (a bad pair stops before the run dir changes), model, optimizer, resume
    ev: dict[str, float] = {}
    for step in range(run.start, cfg.max_steps):
        done = step + 1
        # ---- batch: this process's share of the step's pairs, in micro-batches
        idx = loop.batch_indices(len(run.train_pairs), cfg.batch_size, cfg.seed, step,
                                 run.accelerator.process_index, run.accelerator.num_processes)[:run.per_process]
        batch = [run.train_pairs[i] for i in idx]
        micro_batches = [[batch[i] for i in g] for g in pair_groups(batch, run.micro, run.budget)]

        def loss_fn(chunk):  # chosen and rejected of every pair in one forward
            r = pair_rewards(run.model, chunk, run.pad_id)  # (2b,)
            loss, m = bradley_terry_loss(r[: len(chunk)], r[len(chunk):])
            return loss * (len(chunk) / len(idx)), m

        # ---- update
        saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
        with loop.naming_checkpoint(run.ckpt):
            m = loop.optimizer_step(run.accelerator, run.model, run.optimizer, run.scheduler, micro_batches, loss_fn,
                                    cfg.max_grad_norm, done)
            if saving:
                loop.check_weights(done, run.model)
        # ---- log
        if done % cfg.log_every == 0 or done == cfg.max_steps:
            run.metrics.log(done, m)
        # ---- eval: held-out pair accuracy and margin
        if done == cfg.max_steps or (cfg.eval_every and done % cfg.eval_every == 0):
            ev = heldout_metrics(run.model, run.eval_pairs, run.pad_id, run.micro, run.budget)
            run.metrics.log(done, ev, console=False)
            if ev:
                run.say(f"[rm] step {done}: held-out pair accuracy {ev['eval/accuracy']:.3f}, "
                        f"margin {ev['eval/margin']:.3f}")
        # ---- checkpoint
        if saving:
            run.ckpt.save(done, run.model, run.optimizer, run.scheduler, {"step": done})
    return finish(run, ev)


# ----------------------------------------------------------------------------- setup and the end of a run
@dataclass(kw_only=True)
class RMRun:
    """What a run holds between steps (`setup`)."""

    res: Resolved
    cfg: RMConfig
    accelerator: Accelerator
    say: Callable[[str], None]  # prints on the main process
    run_dir: Path
    main: bool
    tokenizer: PreTrainedTokenizerBase
    pad_id: int
    model: torch.nn.Module  # as accelerate prepared it
    train_pairs: list[TokenizedPair]
    eval_pairs: list[TokenizedPair]
    micro: int  # pairs per micro-batch at most
    budget: int  # padded tokens per micro-batch (memory)
    per_process: int  # pairs per process of a batch
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    ckpt: loop.Checkpointer
    metrics: loop.MetricsLog
    start: int  # the first step (resume)
    t0: float  # when the loop began (eval.json's seconds)


def setup(res: Resolved, cfg: RMConfig, ensure) -> RMRun:
    """The pairs first (a bad pair stops the run before the run dir changes), then the SFT model with its new score
    head (LoRA: adapters on the transformer, the head trained fully), the optimizer and the resumed state."""
    from posttrain.models import load_reward_init, maybe_lora, token_budget

    run_dir = res.stage_dir()
    sft_dir, tokenizer, train_pairs, eval_pairs, source = load_pairs(res, cfg, ensure)
    pad_id = tokenizer.pad_token_id
    accelerator, say = loop.start_run(res, cfg.seed, cfg.resume)
    # LoRA: adapters on the transformer, the new score head trained fully (peft's SEQ_CLS modules_to_save)
    model = maybe_lora(res, load_reward_init(sft_dir, pad_id, cfg.seed, accelerator.device, res.model.dtype), say,
                       "SEQ_CLS")
    micro = cfg.micro_batch_size or cfg.batch_size
    budget = token_budget(res.run.micro_batch_tokens, model)  # padded tokens per micro-batch (memory)
    per_process = max(1, cfg.batch_size // accelerator.num_processes)
    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps, cfg.schedule, cfg.min_lr_ratio)
    model, optimizer = accelerator.prepare(model, optimizer)
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.open_metrics(res, cfg.max_steps, accelerator.is_main_process, "[rm] ")
    start = loop.resume_run(ckpt, metrics, model, optimizer, scheduler, resume=cfg.resume, say=say, tag="rm")["step"]
    say(f"[rm] {len(train_pairs)} training pairs from {source}, {len(eval_pairs)} held-out, batch {cfg.batch_size} "
        f"(micro {micro} pairs, <= {budget} tokens), {cfg.max_steps} steps, lr {cfg.lr}")
    return RMRun(res=res, cfg=cfg, accelerator=accelerator, say=say, run_dir=run_dir,
                 main=accelerator.is_main_process, tokenizer=tokenizer, pad_id=pad_id, model=model,
                 train_pairs=train_pairs, eval_pairs=eval_pairs, micro=micro, budget=budget, per_process=per_process,
                 optimizer=optimizer, scheduler=scheduler, ckpt=ckpt, metrics=metrics, start=start, t0=time.time())


def finish(run: RMRun, ev: dict[str, float]) -> Path:
    """final/ (every process gathers a sharded model; the main process saves) and eval.json with the held-out pair
    metrics (`ev`, the last step's; measured here when a resumed run had no step left); returns final/."""
    from posttrain.models import save_model

    final = run.run_dir / "final"
    whole = loop.full_state_dict(run.accelerator, run.model)  # every process: gathers a sharded model (FSDP, ZeRO-3)
    if run.main:
        save_model(run.accelerator.unwrap_model(run.model), run.tokenizer, final, state_dict=whole)
        if run.start == run.cfg.max_steps:  # resumed at the end: no step measured it
            ev = heldout_metrics(run.model, run.eval_pairs, run.pad_id, run.micro, run.budget)
        loop.write_json(run.run_dir / "eval.json", {"model": str(final), "heldout": ev,
                                                    "train_pairs": len(run.train_pairs),
                                                    "seconds": round(time.time() - run.t0, 1)})
        run.say(f"[rm] saved {final}" + (f" (held-out pair accuracy {ev['eval/accuracy']:.3f} on "
                                         f"{len(run.eval_pairs)} pairs)" if ev else ""))
        run.metrics.close(ev)
    run.metrics.close()
    run.accelerator.wait_for_everyone()
    return final


# ----------------------------------------------------------------------------- data and the held-out metrics
def load_pairs(res: Resolved, cfg: RMConfig,
               ensure) -> tuple[Path, Any, list[TokenizedPair], list[TokenizedPair], str]:
    """(SFT model dir, tokenizer, training pairs, held-out pairs, their source), checked: on_bad_rows=error stops
    on what needs no tokenizer before SFT may have to run."""
    from posttrain import preferences
    from posttrain.models import load_tokenizer

    train_rows, eval_rows, source, eval_source = preferences.training_pairs(ensure, cfg.train_file, cfg.eval_file,
                                                                            seed=cfg.seed,
                                                                            columns=res.task.columns.mapping())
    if cfg.on_bad_rows == "error":  # fail fast on what needs no tokenizer, before SFT may have to run
        preferences.check_pairs(train_rows, source, "error")
        preferences.check_pairs(eval_rows[: cfg.eval_pairs], eval_source, "error")
    sft_dir = ensure("sft")
    tokenizer = load_tokenizer(sft_dir, res.model)
    append_eos = rm_appends_eos(tokenizer)
    _, train_pairs, bad = preferences.check_pairs(train_rows, source, cfg.on_bad_rows, tokenizer,
                                                  res.model.max_length, append_eos=append_eos)
    if bad.count:
        print(f"[rm] {bad.summary()}")
    _, eval_pairs, bad = preferences.check_pairs(eval_rows[: cfg.eval_pairs], eval_source, cfg.on_bad_rows,
                                                 tokenizer, res.model.max_length, append_eos=append_eos)
    if bad.count:
        print(f"[rm] held-out pairs: {bad.summary()}")
    if len(train_pairs) < cfg.batch_size:
        raise loop.TrainingError(f"only {len(train_pairs)} usable preference pairs in {source}, fewer than "
                                 f"batch_size={cfg.batch_size}")
    return sft_dir, tokenizer, train_pairs, eval_pairs, source


@torch.no_grad()
def heldout_metrics(model, pairs: list[TokenizedPair], pad_id: int, micro: int, max_tokens: int = 0) -> dict[str, float]:
    """Bradley-Terry loss, pair accuracy and margin over held-out pairs."""
    if not pairs:
        return {}
    model.eval()
    sums: dict[str, float] = {}
    for chunk in ([pairs[i] for i in g] for g in pair_groups(pairs, micro, max_tokens)):
        r = pair_rewards(model, chunk, pad_id)
        loss, m = bradley_terry_loss(r[: len(chunk)], r[len(chunk):])
        m["loss"] = float(loss)
        for k, v in m.items():
            sums[k] = sums.get(k, 0.0) + v * len(chunk)
    model.train()
    return {f"eval/{k}": v / len(pairs) for k, v in sums.items()}
