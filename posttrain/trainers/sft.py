"""Supervised fine-tuning (stage 0): next-token loss on completions, prompt tokens masked.

CPU:        posttrain sft --recipe tiny-summarize            (~4-5 min on 2 cores, from nothing)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain sft --recipe tiny-summarize model.path=/path/to/hf-model

Reads top to bottom: `setup` (data, then the model), loop { batch -> loss -> optimizer step -> log -> eval / samples
-> checkpoint }, `finish` (final/ in Hugging Face format; the task's gold metric next to the untrained model's).

Details:
- Completion-only loss: the mean over completion tokens (eos included) of -log p(token); prompt and padding tokens
  are masked (`completion_mask`). The mean is over all completion tokens of the optimizer batch, so gradient
  accumulation gives the same gradient as one big batch (not a mean of per-micro-batch means).
- `prompt_loss_weight` adds prompt tokens to the loss with that weight (as OpenAI's fine-tuning API once did): for a
  preset built from scratch, which has never seen language, the documents are the only pretraining signal and teach
  in-context copying (names repeat within a document) that a summariser needs (the tiny-summarize recipe sets 0.1);
  with a pretrained model leave it at 0.
- Chat templates, conversational rows and rows too long for model.max_length: see `setup`.
- Log-probs come from `posttrain.logprobs` (the single implementation); samples and the final evaluation come from
  the rollout engine (nothing here calls `model.generate`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Literal

import torch

from posttrain import loop
from posttrain.chat import prompt_text
from posttrain.config import Resolved
from posttrain.data import collate_completions, to_device, token_groups, tokenize_completions
from posttrain.logprobs import nll_sum, token_weights

if TYPE_CHECKING:  # the annotations of the run object only
    from accelerate import Accelerator
    from transformers import PreTrainedTokenizerBase


@dataclass
class SFTConfig(loop.TrainingConfig):
    batch_size: int = 32
    """Sequences per optimizer step (global, across processes)."""
    eval_loss_rows: int = 128
    """Held-out rows used for the periodic eval loss."""
    num_samples: int = 2
    """Held-out prompts whose greedy completions are printed at each eval."""
    final_eval_rows: int = 100
    """Held-out prompts scored with the task's gold metric after training (0 skips)."""
    max_new_tokens: int = 64
    """Generation budget for samples and the final evaluation."""
    prompt_loss_weight: float = 0.0
    """Weight of prompt tokens in the loss (0: completion-only). A small weight helps a model trained from scratch."""
    # loop.TrainingConfig's fields (one docstring each, there) whose default is this trainer's own:
    lr: float = 3e-3
    max_steps: int = 400
    schedule: Literal["cosine", "linear", "constant"] = "cosine"
    log_every: int = 20
    eval_every: int = 100
    save_every: int = 100
    warmup_steps: int = 20
    min_lr_ratio: float = 0.1


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """Fine-tune the base model (`ensure("base")`: a preset built from scratch or a local HF dir)
    on the task; returns the final model directory."""
    cfg: SFTConfig = res.stage_cfg
    run = setup(res, cfg, ensure)  # data first (a bad row stops before any model loads), model, optimizer, resume
    accelerator = run.accelerator
    tokens_seen, t_last = 0, time.time()
    for step in range(run.start, cfg.max_steps):
        # ---- batch: this process's share of the step's rows, in micro-batches
        idx = loop.batch_indices(len(run.train_pairs), cfg.batch_size, cfg.seed, step,
                                 accelerator.process_index, accelerator.num_processes)[:run.per_process]
        micro_batches = [collate_completions(c, run.tokenizer.pad_token_id)
                         for c in micro_groups([run.train_pairs[i] for i in idx], run.micro, run.budget)]
        # counted on the host, before the batch moves to the model's device (no device-to-host sync)
        n_tokens = sum(float(token_weights(mb, cfg.prompt_loss_weight).sum()) for mb in micro_batches)
        tokens_seen += int(sum(int(mb["attention_mask"].sum()) for mb in micro_batches))
        micro_batches = [to_device(mb, accelerator.device) for mb in micro_batches]
        # ---- update: token mean over the GLOBAL batch: DDP averages gradients over processes, so each process
        # divides its token-loss sum by the global token count times the number of processes.
        scale = accelerator.num_processes / loop.global_sum(accelerator, n_tokens)

        def loss_fn(mb):
            s, _ = nll_sum(run.model, mb, cfg.prompt_loss_weight)
            return s * scale, {}

        m = loop.optimizer_step(accelerator, run.model, run.optimizer, run.scheduler, micro_batches, loss_fn,
                                cfg.max_grad_norm, step)
        done = step + 1
        # ---- log
        if done % cfg.log_every == 0 or done == cfg.max_steps:
            dt = time.time() - t_last
            run.metrics.log(done, {"loss": m["loss"], "lr": m["lr"], "grad_norm": m["grad_norm"],
                                   "tokens_per_s": tokens_seen / max(dt, 1e-9)})
            tokens_seen, t_last = 0, time.time()
        # ---- eval: held-out loss, and samples
        if cfg.eval_every and (done % cfg.eval_every == 0 or done == cfg.max_steps):
            evaluate(run, done)
        # ---- checkpoint
        if (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps:
            run.ckpt.save(done, run.model, run.optimizer, run.scheduler, {"step": done})
    return finish(run)


# ----------------------------------------------------------------------------- setup, eval and the end of a run
@dataclass(kw_only=True)
class SFTRun:
    """What a run holds between steps (`setup`)."""

    res: Resolved
    cfg: SFTConfig
    accelerator: Accelerator
    say: Callable[[str], None]  # prints on the main process
    run_dir: Path
    base_dir: Path
    tokenizer: PreTrainedTokenizerBase
    model: torch.nn.Module  # as accelerate prepared it
    train_pairs: list[tuple]
    eval_pairs: list[tuple]
    eval_rows: list[dict]
    micro: int  # rows per micro-batch at most
    budget: int  # padded tokens per micro-batch (memory)
    per_process: int  # rows per process of a batch
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    ckpt: loop.Checkpointer
    metrics: loop.MetricsLog
    start: int  # the first step (resume)
    sharded: bool  # the model is sharded over several processes (FSDP, ZeRO-3)


def setup(res: Resolved, cfg: SFTConfig, ensure) -> SFTRun:
    """Data first (a bad row must stop the run before any model loads or any run dir changes), then the base
    model, the tokenized rows, the optimizer and the resumed state.

    - Prompts go through the model's chat template when its tokenizer has one (`posttrain.chat`: a local instruct
      checkpoint as model.path); the eos appended to completions is then its end-of-turn token (e.g. Qwen's
      <|im_end|>).
    - Conversational rows (`data.normalize_row`): a `messages` row trains every assistant turn, a conversational
      prompt/completion row its completion's; the turns are located in the chat template's rendering
      (`chat.encode_conversation`), each trained through its eos, and the rest of the conversation is prompt.
    - Rows longer than model.max_length are dropped with a count (never silently truncated: a truncated completion
      would teach the model to stop without eos)."""
    from posttrain import tasks
    from posttrain.lean.support import sharded_problem
    from posttrain.models import load_model, load_tokenizer, maybe_lora, token_budget

    run_dir = res.stage_dir()
    train_rows = tasks.load_split(res.task, "train")
    eval_rows = tasks.load_split(res.task, "eval")
    base_dir = ensure("base")

    accelerator, say = loop.start_run(res, cfg.seed, cfg.resume)

    tokenizer = load_tokenizer(base_dir, res.model)
    model = maybe_lora(res, load_model(base_dir, res.model.dtype, device=accelerator.device), say)
    train_pairs, dropped = tokenize_completions(train_rows, tokenizer, res.model.max_length)
    eval_pairs, _ = tokenize_completions(eval_rows[: cfg.eval_loss_rows], tokenizer, res.model.max_length)
    if dropped:
        say(f"[sft] dropped {dropped}/{len(train_rows)} training rows longer than model.max_length={res.model.max_length}")
    if len(train_pairs) < cfg.batch_size:
        raise loop.TrainingError(f"only {len(train_pairs)} usable training rows, fewer than batch_size={cfg.batch_size}")

    micro = cfg.micro_batch_size or cfg.batch_size
    budget = token_budget(res.run.micro_batch_tokens, model)  # padded tokens per micro-batch (memory)
    per_process = max(1, cfg.batch_size // accelerator.num_processes)
    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps, cfg.schedule, cfg.min_lr_ratio)
    model, optimizer = accelerator.prepare(model, optimizer)
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.open_metrics(res, cfg.max_steps, accelerator.is_main_process, "[sft] ")

    start = loop.resume_run(ckpt, metrics, model, optimizer, scheduler, resume=cfg.resume, say=say, tag="sft")["step"]

    say(f"[sft] {len(train_pairs)} training rows, batch {cfg.batch_size} (micro {micro} rows, <= {budget} "
        f"tokens), {cfg.max_steps} steps, "
        f"lr {cfg.lr}, {accelerator.num_processes} process(es) on {accelerator.device}")
    # A model sharded over several processes (FSDP, ZeRO-3) runs its forward only when every process does: the
    # main process alone cannot generate samples with it (it would wait for the others forever).
    sharded = accelerator.num_processes > 1 and sharded_problem(accelerator.unwrap_model(model)) is not None
    if sharded and cfg.eval_every and cfg.num_samples:
        say(f"[sft] no samples during training: the model is sharded over {accelerator.num_processes} processes; "
            f"the final evaluation runs on final/")
    return SFTRun(res=res, cfg=cfg, accelerator=accelerator, say=say, run_dir=run_dir, base_dir=base_dir,
                  tokenizer=tokenizer, model=model, train_pairs=train_pairs, eval_pairs=eval_pairs, eval_rows=eval_rows,
                  micro=micro, budget=budget, per_process=per_process, optimizer=optimizer, scheduler=scheduler,
                  ckpt=ckpt, metrics=metrics, start=start, sharded=sharded)


def evaluate(run: SFTRun, done: int) -> None:
    """The held-out loss (every process), logged at `done`; samples of the first prompts (main process)."""
    from posttrain import evaluation

    cfg, accelerator = run.cfg, run.accelerator
    el = eval_loss(run.model, run.eval_pairs, run.tokenizer.pad_token_id, run.micro, run.budget)
    run.metrics.log(done, {"eval_loss": el}, console=False)
    run.say(f"[sft] step {done}: eval loss {el:.4f}")
    if cfg.num_samples and accelerator.is_main_process and not run.sharded:
        show = run.eval_rows[: cfg.num_samples]
        outs = evaluation.complete(accelerator.unwrap_model(run.model), run.tokenizer, [r["prompt"] for r in show],
                                   max_new_tokens=cfg.max_new_tokens)
        for r, o in zip(show, outs):
            run.say(f"    prompt: ...{prompt_text(r['prompt'])[-60:]!r}\n    sample: {o!r}")


def finish(run: SFTRun) -> Path:
    """final/ (every process gathers a sharded model; the main process saves), then the task's gold metric of
    the untrained and the trained model on held-out prompts (eval.json); returns final/."""
    from posttrain import evaluation
    from posttrain.models import load_model, save_model

    cfg, res, accelerator, model, tokenizer = run.cfg, run.res, run.accelerator, run.model, run.tokenizer
    final = run.run_dir / "final"
    whole = loop.full_state_dict(accelerator, model)  # every process: gathers a sharded model (FSDP, ZeRO-3)
    if accelerator.is_main_process:
        save_model(accelerator.unwrap_model(model), tokenizer, final, state_dict=whole)
        run.say(f"[sft] saved {final}")
        if cfg.final_eval_rows:
            rows = run.eval_rows[: cfg.final_eval_rows]
            untrained = load_model(run.base_dir, res.model.dtype, device=accelerator.device)
            before = evaluation.evaluate_model(res.task.name, untrained, tokenizer, rows,
                                               max_new_tokens=cfg.max_new_tokens)
            # sharded: the whole weights are in final/ (the in-memory model holds this process's shard)
            trained = load_model(final, res.model.dtype, device=accelerator.device) if whole is not None \
                else accelerator.unwrap_model(model)
            after = evaluation.evaluate_model(res.task.name, trained, tokenizer, rows,
                                              max_new_tokens=cfg.max_new_tokens)
            loop.write_json(run.run_dir / "eval.json", {"untrained": before, "sft": after})
            run.say(evaluation.format_comparison({"untrained": before, "sft": after}, res.task.name))
            run.metrics.close({"untrained": before, "sft": after})
    run.metrics.close()
    accelerator.wait_for_everyone()
    return final


# ----------------------------------------------------------------------------- micro-batches and the held-out loss
def micro_groups(pairs, micro_batch_size: int, max_tokens: int) -> list[list]:
    """`data.tokenize_completions` items in micro-batches of at most `micro_batch_size` rows and `max_tokens`
    padded tokens, rows of like length together (`data.token_groups`)."""
    groups = token_groups([(0, len(x[0]) + len(x[1])) for x in pairs], micro_batch_size, max_tokens, by_length=True)
    return [[pairs[i] for i in g] for g in groups]


@torch.no_grad()
def eval_loss(model, pairs, pad_id: int, micro_batch_size: int, max_tokens: int = 0) -> float:
    model.eval()
    total, count = 0.0, 0
    for chunk in micro_groups(pairs, micro_batch_size, max_tokens):
        s, n = nll_sum(model, collate_completions(chunk, pad_id))
        total += float(s)
        count += float(n)
    return total / max(1, count)
