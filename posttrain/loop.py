"""Pieces of a training loop on accelerate: setup, optimizer step, metrics, atomic checkpoints, resume.

Every trainer composes these; none of them owns the loop. The same code runs on one CPU
process and under `accelerate launch` (DDP/FSDP/DeepSpeed): the Accelerator decides.

- `setup(seed, threads)`: seeds python/numpy/torch, tunes glibc malloc, creates the `Accelerator`.
- `start_run(res, seed, resume)`: with several processes and an `auto` precision setting, process 0's bf16
  probe for all (`share_bf16_probe`); `setup`, then the run directory and its config.yaml (main process), and
  with an `auto` precision setting precision.json, the bf16 decision that a resume keeps (`recorded_bf16`);
  returns the accelerator and `say` (prints on the main process only).
- `resume_run(...)`: with resume=true, the newest checkpoint restored in place and the metrics rows
  logged after it dropped; returns its step and extra state (step 0 when starting fresh).
- `weights_finite` / `check_weights`, and `naming_checkpoint`: a TrainingError raised inside it is re-raised
  with where the last good checkpoint is (which stays intact).
- `TrainingBase` / `TrainingConfig`: the optimizer, schedule, logging and checkpoint fields every trainer's config
  shares, defined here once (PPO's config takes the first's 11, the other trainers' the second's 14).
- `build_optimizer` / `build_scheduler`: AdamW (no weight decay on norms, biases and
  embeddings), linear warmup then cosine / linear / constant.
- `optimizer_step`: gradient accumulation over micro-batches (no gradient sync on all but
  the last under DDP), clipping (inside the fused AdamW step where it can: `clip_divisor`), a
  non-finite-loss guard, optimizer + scheduler step; metrics averaged over micro-batches and
  processes, or weighted by each micro-batch's share (`weights`).
- `batch_indices`: the data order as a pure function of (seed, step), so resuming at a
  step reproduces the exact batches without saving a sampler.
- `stream_seed(seed, purpose, *indices)`: the seed of one named stream of randomness (a step's samples, a
  pass's row order, ...), a stable hash of its name and indices: every stream a trainer draws from comes
  from here, so two purposes never share one and none depends on a hand-picked prime.
- `MetricsLog`: one JSON line per logged step in metrics.jsonl plus a console line.
- `Checkpointer`: `checkpoints/step-NNNNNN/` written to a temp dir then renamed (atomic);
  it holds model, optimizer, scheduler, RNG states and the data position; `resume_run` loads
  the newest complete one. A checkpoint the disk has no room for first drops the old ones this save would
  drop anyway (never the newest), then stops the run with a TrainingError naming the sizes; a disk that fills
  during the write does the same, its temp dir removed, the earlier checkpoints intact.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import random
import shutil
import time
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Literal

import numpy as np
import torch

from posttrain.errors import ConfigError, TrainingError
from posttrain.models import out_of_disk, tensor_bytes
from posttrain.runtime import (BF16_MIN_SPEEDUP, adopt_bf16_speedup, bf16_forced, bf16_measured, bf16_speedup,
                               has_accelerator_device, native_bf16, probe_decides_bf16, set_threads, tune_malloc)
from posttrain.runtime import mixed_precision as resolve_mixed_precision
from posttrain.trackers import Trackers, flat_config



# ----------------------------------------------------------------------------- the training-config block
@dataclass
class TrainingBase:
    """The optimizer, schedule, logging and checkpoint fields of every trainer's config, defined once.

    A trainer's config inherits them and re-declares (type and default, no docstring) those whose default is its
    own, e.g. `lr: float = 3e-3` in SFTConfig; its YAML keys are the same either way. `posttrain STAGE --help`
    lists them after the trainer's own fields. PPO's config takes these 11; the other trainers' `TrainingConfig`'s 14.
    """

    lr: float = 1e-4
    """Peak learning rate (AdamW; PPO: the policy's, `value_lr` the value model's)."""
    weight_decay: float = 0.0
    """AdamW weight decay (not applied to norms, biases and embeddings)."""
    max_steps: int = 100
    """Training steps: optimizer steps (sft, rm, dpo), batches of rollouts (grpo, distill), iterations (ppo)."""
    schedule: Literal["cosine", "linear", "constant"] = "constant"
    """Learning-rate schedule after warmup, over every optimizer update of the run."""
    max_grad_norm: float = 1.0
    """Gradient clipping norm (of each model; 0 disables)."""
    log_every: int = 1
    """Steps between console metric lines (sft, rm, dpo and ppo write metrics.jsonl at the same steps; grpo and
    distill every step)."""
    eval_every: int = 20
    """Steps between periodic held-out evaluations (what each trainer evaluates: its module docstring); 0: none
    (the evaluation before and after training is `final_eval_rows`', where the trainer has one)."""
    save_every: int = 50
    """Steps between checkpoints (0: only at the end)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (oldest deleted first)."""
    seed: int = 0
    """Seed of the stage's randomness: data or prompt order, sampling, init-time draws (each from its own stream,
    `stream_seed`)."""
    resume: bool = False
    """Continue from the newest checkpoint in the run directory."""


@dataclass
class TrainingConfig(TrainingBase):
    """`TrainingBase` and three fields PPO fixes for itself (no warmup, linear decay to 0, micro-batches by tokens)."""

    micro_batch_size: int = 0
    """Rows per forward pass at most (gradient accumulation; a preference pair counts as one and is 2 rows); 0: no
    row cap (`run.micro_batch_tokens` still caps their padded tokens)."""
    warmup_steps: int = 0
    """Linear warmup, in optimizer updates."""
    min_lr_ratio: float = 0.0
    """Final learning rate as a fraction of the peak (cosine / linear)."""


# ----------------------------------------------------------------------------- setup
def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def setup(seed: int, threads: int = 0, mixed_precision: str | None = None):
    """Seed everything and return an `accelerate.Accelerator` (CPU unless launched on GPUs).

    mixed_precision None: what `accelerate launch` was given (its config file or --mixed_precision), else "no".
    """
    from accelerate import Accelerator

    tune_malloc()  # faster forwards on CPU (see its docstring); process-wide, once
    set_threads(threads)
    # Without a GPU, ask for the CPU explicitly: then `accelerate launch --multi_gpu --num_processes N` or
    # `torchrun --nproc_per_node N` (which set LOCAL_RANK / WORLD_SIZE) give N CPU processes over gloo
    # (accelerate's MULTI_CPU) instead of N unconnected single-process runs.
    from accelerate.state import AcceleratorState

    # Each stage is a run of its own: chained stages (and tests) in one process may ask for another mixed
    # precision, which accelerate's process-wide state refuses to change; the process group (PartialState) stays.
    AcceleratorState._reset_state(reset_partial_state=False)
    accelerator = Accelerator(mixed_precision=mixed_precision, cpu=not has_accelerator_device())
    seed_everything(seed)
    return accelerator


def share_bf16_probe() -> None:
    """Several CPU processes (`accelerate launch`, torchrun: WORLD_SIZE > 1): process 0 runs the bf16 probe and
    every process adopts its ratio (`runtime.adopt_bf16_speedup`), so the `auto` settings choose one precision on
    all ranks. Each rank's own probe, timed while the others load, can fall on either side of BF16_MIN_SPEEDUP,
    and the ranks would then train one DDP model in two precisions and sample in two dtypes. Starts the process
    group (accelerate's PartialState, which the Accelerator then reuses). A no-op in one process and wherever
    no probe decides (`runtime.probe_decides_bf16`: POSTTRAIN_BF16 or a resumed run's pin, a GPU, a CPU
    without bf16 units)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or not probe_decides_bf16():
        return
    from accelerate import PartialState
    from accelerate.utils import broadcast_object_list

    ratio = [bf16_speedup() if PartialState(cpu=True).is_main_process else None]
    broadcast_object_list(ratio, from_process=0)
    adopt_bf16_speedup(ratio[0])


def main_printer(accelerator) -> Callable[..., None]:
    """`print` on the main process, a no-op on the others (what a trainer's `say` is)."""
    return print if accelerator.is_main_process else _silent


def _silent(*args, **kwargs) -> None:
    return None


def start_run(res, seed: int, resume: bool, check: Callable[[Any], None] | None = None):
    """Start a stage's run: `setup` (seeds, threads, the Accelerator), `check(accelerator)` (settings that depend on
    the number of processes: a ConfigError there leaves every directory as it was), then on the main process its
    run directory (`prepare_run_dir`: an earlier run is kept as <dir>.prev unless resuming) and the resolved
    config.yaml, every process waiting for that. Returns (accelerator, say)."""
    from posttrain.config import save_resolved

    set_threads(res.run.threads)  # first: `auto` measures bf16 against fp32 at the run's thread count
    if "auto" in (res.run.mixed_precision, res.rollout.dtype):
        share_bf16_probe()
    accelerator = setup(seed, res.run.threads, resolve_mixed_precision(res.run.mixed_precision))
    if check is not None:
        check(accelerator)
    say = main_printer(accelerator)
    set_progress_quiet(res.run.quiet or not accelerator.is_main_process)
    auto = "auto" in (res.run.mixed_precision, res.rollout.dtype)
    forced = bf16_forced() if auto else None
    measured = bf16_measured() if auto and forced is None and accelerator.device.type == "cpu" else None
    if forced is not None:
        say(f"[run] the auto settings use {'bf16' if forced[0] else 'fp32'}: {forced[1]}")
    elif measured is not None and res.run.mixed_precision == "auto":  # the probe ran (the CPU lists bf16 units)
        say(f"[run] run.mixed_precision=auto: bf16 matmuls measured {measured:.2f}x fp32 here "
            f"({'bf16' if accelerator.mixed_precision == 'bf16' else 'fp32'}; bf16 needs >= {BF16_MIN_SPEEDUP}x)")
    if accelerator.mixed_precision != "no":
        say(f"[run] {accelerator.mixed_precision} autocast over fp32 weights (run.mixed_precision="
            f"{res.run.mixed_precision}); generation is not autocast (rollout.dtype={res.rollout.dtype})")
    if accelerator.is_main_process:
        prepare_run_dir(res.stage_dir(), resume, say)
        save_resolved(res, res.stage_dir() / "config.yaml")
        record = res.stage_dir() / PRECISION_FILE
        if auto and not (resume and record.exists()):  # what `auto` chose, for a resume to keep (recorded_bf16)
            write_json(record, {"bf16": native_bf16(), "decided_by": forced[1] if forced else
                                "probe" if measured is not None else "hardware", "bf16_speedup": measured,
                                "threads": torch.get_num_threads()})
    accelerator.wait_for_everyone()
    return accelerator, say


PRECISION_FILE = "precision.json"


def recorded_bf16(run_dir: Path) -> bool | None:
    """The bf16 decision of the `auto` settings that the run in `run_dir` started with (`start_run` records it in
    precision.json), or None (no record: the run had no auto setting, or predates the record). The CLI pins it on
    resume=true (`runtime.pin_bf16`), so the continued run computes in the precision it began in."""
    path = Path(run_dir) / PRECISION_FILE
    if not path.is_file():
        return None
    try:
        value = json.loads(path.read_text()).get("bf16")
    except (ValueError, AttributeError) as e:
        raise ConfigError(f"{path}: not the JSON object posttrain wrote ({e}); delete it to let the resumed run "
                          "decide bf16 afresh") from None
    return value if isinstance(value, bool) else None


def global_sum(accelerator, value: float) -> float:
    """`value` summed over all processes (itself when there is one), e.g. the tokens of a global batch."""
    if accelerator is None or accelerator.num_processes == 1:
        return float(value)
    t = torch.tensor([float(value)], dtype=torch.float64, device=accelerator.device)
    return float(accelerator.reduce(t, reduction="sum")[0])


# ----------------------------------------------------------------------------- optimisation
def build_optimizer(model: torch.nn.Module, lr: float, weight_decay: float = 0.0,
                    betas: tuple[float, float] = (0.9, 0.95), eps: float = 1e-8) -> torch.optim.Optimizer:
    decay, no_decay = [], []
    for name, p in model.named_parameters():
        if not p.requires_grad:
            continue
        (decay if p.ndim >= 2 and "embed" not in name else no_decay).append(p)
    groups = [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    groups = [g for g in groups if g["params"]]
    # The fused kernel (one pass per tensor, CPU and CUDA) when every parameter allows it: much faster than the
    # per-tensor loop on the tiny presets' many small tensors (docs/results-archive.md, "Lean forwards").
    params = decay + no_decay
    fused = bool(params) and all(p.is_floating_point() and p.device.type in ("cpu", "cuda") for p in params) \
        and len({(p.device.type, p.dtype) for p in params}) == 1
    optimizer = torch.optim.AdamW(groups, lr=lr, betas=betas, eps=eps, fused=fused or None)
    if fused:
        # The fused kernel writes the weights without bumping their version counters, which is how the rollout
        # engine sees that a model changed since its cached fused weights (models.weights_signature).
        from torch.autograd.graph import increment_version

        optimizer.register_step_post_hook(lambda opt, args, kwargs: increment_version(params))
    return optimizer


def lr_factor(step: int, warmup_steps: int, total_steps: int, schedule: str, min_lr_ratio: float) -> float:
    """Multiplier of the peak learning rate at `step` (0-based)."""
    if warmup_steps > 0 and step < warmup_steps:
        return (step + 1) / warmup_steps
    if schedule == "constant":
        return 1.0
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    if schedule == "linear":
        return min_lr_ratio + (1 - min_lr_ratio) * (1 - progress)
    if schedule == "cosine":
        return min_lr_ratio + (1 - min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))
    raise ValueError(f"unknown schedule {schedule!r}")


def build_scheduler(optimizer, warmup_steps: int, total_steps: int, schedule: str = "cosine",
                    min_lr_ratio: float = 0.1):
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: lr_factor(s, warmup_steps, total_steps, schedule, min_lr_ratio))


def metric_extreme(name: str) -> str:
    """"max" / "min" for a metric reduced by its extreme over micro-batches and processes, else ""."""
    leaf = name.rsplit("/", 1)[-1]
    return "max" if name.endswith("_max") or leaf.startswith("max_") else "min" if leaf.startswith("min_") else ""


def nonfinite_grads(model, show: int = 3) -> str:
    """" (non-finite gradients in NAME, ... (k of n parameters))" for an error message, or "" (read on the error
    path only: one host sync per parameter)."""
    named = [(n, p.grad) for n, p in model.named_parameters() if p.grad is not None]
    bad = [n for n, g in named if not bool(torch.isfinite(g).all())]
    if not bad:
        return ""
    return f" (non-finite gradients in {', '.join(bad[:show])}{', ...' if len(bad) > show else ''}: {len(bad)} of " \
        f"{len(named)} parameters)"


def total_norm(grads: list[torch.Tensor]) -> torch.Tensor:
    """The 2-norm of all `grads` as one vector (0-dim fp32; 0 for none), as `clip_grad_norm_` computes it."""
    if not grads:
        return torch.zeros(())
    if hasattr(torch.nn.utils, "get_total_norm"):  # torch >= 2.6: foreach norms where the device has them
        return torch.nn.utils.get_total_norm(grads).float()
    return torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g, dtype=torch.float32) for g in grads]))


def clip_divisor(norm: torch.Tensor, max_norm: float) -> torch.Tensor:
    """What clipping to `max_norm` divides every gradient by: 1 / min(1, max_norm / (norm + 1e-6)), the
    coefficient `torch.nn.utils.clip_grad_norm_` multiplies them by (0-dim fp32, on norm's device)."""
    coef = torch.clamp(max_norm / (norm.float() + 1e-6), max=1.0)
    return 1.0 / coef


def _fused_clip_target(accelerator, optimizer) -> torch.optim.Optimizer | None:
    """The fused AdamW under `optimizer` when gradient clipping can ride in its step instead of a pass of its own
    (it divides each gradient by its `grad_scale` attribute as it reads it, the hook torch's GradScaler uses):
    one process or DDP (whole, identical gradients on every process), no fp16 loss scaler, and every parameter
    in the fused kernel. Else None: accelerate's clip_grad_norm_ (FSDP and DeepSpeed shard the gradients)."""
    from accelerate.utils import DistributedType

    inner = getattr(optimizer, "optimizer", optimizer)  # accelerate's AcceleratedOptimizer wraps the torch one
    whole = (DistributedType.NO, DistributedType.MULTI_CPU, DistributedType.MULTI_GPU)
    if (getattr(accelerator, "distributed_type", None) not in whole
            or getattr(accelerator, "scaler", None) is not None
            or not isinstance(inner, torch.optim.AdamW) or not inner.defaults.get("fused")
            or getattr(inner, "grad_scale", None) is not None):
        return None
    return inner


def optimizer_step(accelerator, model, optimizer, scheduler, micro_batches: list[Any],
                   loss_fn: Callable[[Any], tuple[torch.Tensor, dict[str, float]]],
                   max_grad_norm: float, step: int, weights: list[float] | None = None) -> dict[str, float]:
    """One optimizer step over `micro_batches` (gradient accumulation).

    `loss_fn(micro_batch)` returns (loss, metrics) where the loss is already scaled to its
    share of the whole batch (e.g. summed token losses / tokens in the batch), so the
    accumulated gradient is that of the batch loss. Metrics are summed over micro-batches
    when their name ends in `_sum`, maxed when it ends in `_max` or its last part starts with `max_`
    (`mismatch/max_ratio`), minimised when that part starts with `min_`, else averaged (over processes too).

    `weights` (one per micro-batch): its share of the GLOBAL batch, all processes' shares summing to 1
    (e.g. its loss tokens / the batch's). The averaged metrics are then the weighted means over the
    micro-batches of every process, so a token-mean metric is the whole batch's token mean. A micro-batch of
    weight 0 (a padding copy that keeps the processes' all-reduces in step) adds nothing to any metric.

    Several processes may bring different numbers of micro-batches (token budgets split long rows finer):
    each runs as many as the most any process has, the extra ones copies of its last with their loss times 0
    (no gradient, no metric), so every process's collectives and DDP's gradient all-reduce line up.
    """
    model.train()
    totals: dict[str, float] = {}
    loss_total = 0.0
    if weights is not None and len(weights) != len(micro_batches):
        raise ValueError(f"optimizer_step: {len(weights)} weights for {len(micro_batches)} micro-batches")
    real = len(micro_batches)
    if accelerator.num_processes > 1:
        most = int(accelerator.gather(torch.tensor([real], device=accelerator.device)).max())
        micro_batches = list(micro_batches) + [micro_batches[-1]] * (most - real)
    for i, mb in enumerate(micro_batches):
        last = i == len(micro_batches) - 1
        ctx = accelerator.no_sync(model) if (not last and accelerator.num_processes > 1) else nullcontext()
        with ctx:
            loss, metrics = loss_fn(mb)
            if i >= real:  # a copy that only keeps this process in step with the others
                loss, metrics = loss * 0.0, {}
            value = float(loss.detach())  # the one read of the loss per micro-batch (a host sync on a GPU)
            finite = math.isfinite(value)
            bad = 0.0 if finite else 1.0
            if accelerator.num_processes > 1:  # every process stops at the same micro-batch, none waits in backward
                bad = global_sum(accelerator, bad)
            if bad:
                optimizer.zero_grad(set_to_none=True)
                where = f"({value})" if not finite else f"on {int(bad)} other process(es)"
                raise TrainingError(f"non-finite loss {where} at step {step}; stopping. "
                                    "The last good checkpoint is intact: lower the learning rate and resume.")
            accelerator.backward(loss)
        loss_total += value
        w = 1.0 if weights is None else float(weights[i]) if i < real else 0.0
        for k, v in metrics.items():
            if metric_extreme(k) == "max":
                v = float(v) if (v == v and w != 0.0) else -math.inf
                totals[k] = max(totals.get(k, -math.inf), v)
            elif metric_extreme(k) == "min":
                v = float(v) if (v == v and w != 0.0) else math.inf
                totals[k] = min(totals.get(k, math.inf), v)
            elif k.endswith("_sum"):
                totals[k] = totals.get(k, 0.0) + (float(v) if w != 0.0 else 0.0)
            else:
                totals[k] = totals.get(k, 0.0) + (float(v) * w if w != 0.0 else 0.0)
    grad_norm = float("nan")
    fused = None
    if max_grad_norm > 0:
        fused = _fused_clip_target(accelerator, optimizer)
        if fused is not None:  # the clip as the fused AdamW's gradient divisor: no pass of its own over the grads
            grads = [p.grad for p in model.parameters() if p.grad is not None]
            norm = total_norm(grads)
            grad_norm = float(norm)
            if math.isfinite(grad_norm):
                scale = clip_divisor(norm, max_grad_norm)
                fused.grad_scale = scale if float(scale) > 1.0 else None
        else:
            grad_norm = float(accelerator.clip_grad_norm_(model.parameters(), max_grad_norm))
        if not math.isfinite(grad_norm):
            where = nonfinite_grads(model)
            optimizer.zero_grad(set_to_none=True)
            raise TrainingError(f"non-finite gradient norm at step {step}{where}; stopping. The last good checkpoint "
                                "is intact.")
    try:
        optimizer.step()
    finally:
        if fused is not None:
            fused.grad_scale = None
    scheduler.step()
    optimizer.zero_grad(set_to_none=True)
    n = real if weights is None else 1  # weighted: the sums are already the means
    out = {k: (v if k.endswith("_sum") or metric_extreme(k) else v / n) for k, v in totals.items()}
    out["loss"] = loss_total
    if accelerator.num_processes > 1:
        # The logged numbers describe the global batch: losses and means averaged over processes (each
        # process's loss is its share scaled up, see loss_fn), weighted means summed (their weights sum
        # to 1 over all processes), `_sum` metrics summed, extremes (`_max`, `max_`, `min_`) maxed or minimised.
        keys = sorted(out)
        t = torch.tensor([out[k] for k in keys], dtype=torch.float64, device=accelerator.device)
        mean = accelerator.reduce(t.clone(), reduction="mean")
        total = accelerator.reduce(t.clone(), reduction="sum")
        gathered = accelerator.gather(t.unsqueeze(0))  # (W, k)
        top, bottom = gathered.max(0).values, gathered.min(0).values  # (k,)
        summed = ("_sum",) if weights is None else ("_sum", "")
        pick = {"max": top, "min": bottom}
        out = {k: float(pick[metric_extreme(k)][i] if metric_extreme(k) else mean[i] if k == "loss"
                        else total[i] if k.endswith(summed) else mean[i]) for i, k in enumerate(keys)}
    out.update(grad_norm=grad_norm, lr=scheduler.get_last_lr()[0])
    return out


def weights_finite(*models) -> bool:
    """Every parameter of every model is finite (checked before a checkpoint or an evaluation)."""
    return all(bool(torch.isfinite(p).all()) for m in models for p in m.parameters())


def check_weights(step: int, *models, unit: str = "step") -> None:
    """A TrainingError when a weight is not finite after `step`: the run stops without saving them."""
    if not weights_finite(*models):
        raise TrainingError(f"non-finite weights after {unit} {step}; stopping without saving them")


@contextmanager
def naming_checkpoint(ckpt: "Checkpointer", context: str = ""):
    """Re-raise a TrainingError from inside with where the last good checkpoint is (it stays intact), so the
    user knows what `resume=true` continues from; `context` (e.g. "PPO iteration 3") goes first."""
    try:
        yield
    except TrainingError as e:
        last = ckpt.latest()
        where = f"last good checkpoint: {last}" if last else "no checkpoint was written yet"
        raise TrainingError(f"{e} ({context + '; ' if context else ''}{where})") from None


# ----------------------------------------------------------------------------- data order
def batch_indices(n: int, batch_size: int, seed: int, step: int, rank: int = 0, world: int = 1) -> list[int]:
    """Indices of the global batch at `step` (this process's shard of it).

    Epochs are fresh seeded permutations; the last incomplete batch of an epoch is dropped.
    A pure function of its arguments: resuming at `step` needs no sampler state.
    """
    if n < batch_size:
        raise ValueError(f"dataset has {n} rows, fewer than batch_size={batch_size}")
    per_epoch = n // batch_size
    epoch, i = divmod(step, per_epoch)
    perm = np.random.default_rng([seed, epoch]).permutation(n)
    idx = perm[i * batch_size:(i + 1) * batch_size]
    return [int(j) for j in idx[rank::world]]


def stream_seed(seed: int, purpose: str, *indices: int) -> int:
    """The 63-bit seed of the stream `purpose` (e.g. "grpo/sample") at `indices` (step, round, pass, ...) of a run
    seeded `seed`: blake2b of a canonical encoding of the three (not Python's `hash`, which is salted per process),
    so it is the same in every process and on every machine, and distinct (purpose, indices) give independent
    seeds. Non-negative and below 2**63: good for `random.Random`, `torch.Generator.manual_seed`,
    `np.random.default_rng`, `SamplingParams.seed` and `batch_indices`. (A run's data order, `batch_indices(...,
    seed, step)`, and PPO's epoch shuffles seed numpy with a list of integers, which numpy hashes itself.)"""
    if not purpose or any(isinstance(x, bool) or not isinstance(x, (int, np.integer)) for x in (seed, *indices)):
        raise ValueError(f"stream_seed needs a purpose and integer seed / indices, got {purpose!r}, {seed!r}, {indices!r}")
    key = json.dumps([purpose, int(seed), *(int(i) for i in indices)], separators=(",", ":")).encode()
    return int.from_bytes(hashlib.blake2b(key, digest_size=8).digest(), "big") >> 1




# ----------------------------------------------------------------------------- metrics
class MetricsLog:
    """metrics.jsonl (one JSON object per logged step) and a console progress line."""

    def __init__(self, path: Path, total_steps: int, enabled: bool = True, quiet: bool = False, prefix: str = "",
                 trackers: "Trackers | None" = None):
        self.path = Path(path)
        self.trackers = trackers if enabled else None  # run.report_to: the same rows, streamed
        self.total = total_steps
        self.enabled = enabled
        self.quiet = quiet
        self.prefix = prefix
        self.t0 = time.time()
        self.start_step = 0
        if enabled:
            self.path.parent.mkdir(parents=True, exist_ok=True)

    def truncate_after(self, step: int) -> None:
        """On resume: drop rows logged after the checkpoint's step (they will be redone)."""
        self.start_step = step
        if self.trackers is not None:
            self.trackers.resume_step = step
        if not (self.enabled and self.path.exists()):
            return
        keep = []
        for line in self.path.read_text().split("\n"):  # only \n ends a JSON Lines row
            try:
                if json.loads(line).get("step", 0) <= step:
                    keep.append(line)
            except json.JSONDecodeError:
                continue  # a torn last line from a killed run
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text("".join(l + "\n" for l in keep))
        tmp.replace(self.path)

    def log(self, step: int, metrics: dict[str, Any], console: bool = True) -> None:
        if not self.enabled:
            return
        row = {"step": step, "time": round(time.time() - self.t0, 3)}
        row.update({k: (float(v) if isinstance(v, (int, float, np.floating)) else v) for k, v in metrics.items()})
        with open(self.path, "a") as f:
            f.write(json.dumps(row) + "\n")
        if self.trackers is not None:
            self.trackers.log(metrics, step)
        if console and not self.quiet:
            done = step - self.start_step
            elapsed = time.time() - self.t0
            eta = elapsed / max(1, done) * max(0, self.total - step)
            shown = " ".join(f"{k} {_fmt(v)}" for k, v in metrics.items() if isinstance(v, (int, float)))
            print(f"{self.prefix}step {step}/{self.total} {shown} | {elapsed:.0f}s elapsed, eta {eta:.0f}s", flush=True)


    def log_table(self, name: str, rows: list[dict[str, Any]], step: int) -> None:
        """A table (a step's saved rollouts) to the trackers that show tables; the JSONL file is the caller's."""
        if self.trackers is not None:
            self.trackers.log_table(name, rows, step)

    def close(self, final: dict[str, Any] | None = None) -> None:
        """Finish the trackers (each stage of a chain is its own tracker run), after sending them the numbers of the
        final evaluation (eval.json's report, as `final/<key>...` at the last step); metrics.jsonl needs nothing.
        Idempotent: a trainer closes once after its report and once on every process."""
        if self.trackers is not None:
            if final:
                flat = flat_config(final, "final/", sep="/")
                self.trackers.log(flat, self.total)
            self.trackers.finish()
            self.trackers = None


def set_progress_quiet(quiet: bool) -> None:
    """Whether `Progress` lines print by default in this process (`start_run` sets it from run.quiet and the rank)."""
    Progress.default_quiet = bool(quiet)


class Progress:
    """A long phase's progress with an ETA, as `generate(progress=...)` reports it: `label: done/total (pct), Ns
    elapsed, eta Ms`, at most every `every_s` seconds and only once the phase has run that long (a short
    evaluation prints nothing), then one closing line if it printed any. `quiet`: print nothing (None: as the
    stage says, `set_progress_quiet`: silent with run.quiet=true and on every process but the main one)."""

    default_quiet = False  # `set_progress_quiet`: run.quiet, or a process other than the main one

    def __init__(self, label: str, every_s: float = 15.0, quiet: bool | None = None,
                 clock: Callable[[], float] = time.time, out: Callable[[str], None] | None = None):
        quiet = Progress.default_quiet if quiet is None else quiet
        self.label, self.every_s, self.quiet, self.clock = label, every_s, quiet, clock
        self.out = out or (lambda line: print(line, flush=True))
        self.t0 = self.last = clock()
        self.printed = False

    def __call__(self, done: int, total: int) -> None:
        now = self.clock()
        if self.quiet or total <= 0:
            return
        if done >= total:
            if self.printed:
                self.out(f"{self.label}: {total}/{total} done in {now - self.t0:.0f}s")
            return
        if now - self.last < self.every_s:
            return
        self.last, self.printed = now, True
        elapsed = now - self.t0
        eta = elapsed / max(done, 1) * (total - done)
        self.out(f"{self.label}: {done}/{total} ({100 * done / total:.0f}%), {elapsed:.0f}s elapsed, eta {eta:.0f}s")


def open_metrics(res, total_steps: int, main: bool, prefix: str) -> MetricsLog:
    """The stage's MetricsLog: `<run_dir>/metrics.jsonl`, the console line, and `run.report_to`'s trackers."""
    run_dir = res.stage_dir()
    tracked = (Trackers(res.run.report_to, run_dir, res.recipe, res.stage, res.to_dict())
               if main and res.run.report_to else None)
    return MetricsLog(run_dir / "metrics.jsonl", total_steps, main, res.run.quiet, prefix=prefix, trackers=tracked)


def _fmt(v: float) -> str:
    if v != v:
        return "nan"
    if v == 0 or 1e-3 <= abs(v) < 1e5:
        return f"{v:.4g}"
    return f"{v:.3e}"


# ----------------------------------------------------------------------------- checkpoints
def _rng_state() -> dict[str, Any]:
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}


def _set_rng_state(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])


def full_state_dict(accelerator, model) -> dict | None:
    """The whole weights of a sharded model, for `models.save_model(..., state_dict=)`, or None when the model's
    parameters are whole tensors already (DDP, one process: save them as they are). Call it on EVERY process (the
    gather is collective); the main process gets the tensors, on the CPU. FSDP2 (DTensor parameters): torch's
    `get_model_state_dict(full_state_dict=True, cpu_offload=True)`; FSDP1 / DeepSpeed ZeRO-3:
    `accelerator.get_state_dict`. `save_pretrained` on FSDP2 parameters fails ("Attempted to access the data
    pointer on an invalid python storage", torch 2.13, seen on the CPU with gloo)."""
    from posttrain.lean.support import sharded_problem

    inner = accelerator.unwrap_model(model) if accelerator is not None else model
    if sharded_problem(inner) is None:
        return None
    if any(type(p).__name__ == "DTensor" for p in inner.parameters()):
        from torch.distributed.checkpoint.state_dict import StateDictOptions, get_model_state_dict

        return get_model_state_dict(inner, options=StateDictOptions(full_state_dict=True, cpu_offload=True))
    return accelerator.get_state_dict(model)


def _newest(ckpts: list[Path]) -> str:
    return f"the newest checkpoint, {ckpts[-1].name}, is intact" if ckpts else "no earlier checkpoint"


class Checkpointer:
    """Atomic checkpoints under `<run_dir>/checkpoints/step-NNNNNN/` (temp dir + rename)."""

    def __init__(self, run_dir: Path, keep: int = 2, accelerator=None):
        self.dir = Path(run_dir) / "checkpoints"
        self.keep = keep
        self.accelerator = accelerator

    @property
    def is_main(self) -> bool:
        return self.accelerator is None or self.accelerator.is_main_process

    def save(self, step: int, model, optimizer=None, scheduler=None, data_state: dict | None = None,
             extra: dict | None = None) -> Path | None:
        if self.accelerator is not None:
            self.accelerator.wait_for_everyone()
        final = self.dir / f"step-{step:06d}"
        # On every process: under FSDP / DeepSpeed ZeRO-3 this gathers the full weights (to the main one).
        model_state = self.accelerator.get_state_dict(model) if self.accelerator is not None else model.state_dict()
        if self.is_main:
            state = {
                "step": step,
                "model": {k: v.detach().cpu() for k, v in model_state.items()},
                "optimizer": optimizer.state_dict() if optimizer is not None else None,
                "scheduler": scheduler.state_dict() if scheduler is not None else None,
                "rng": _rng_state(),
                "data": data_state or {},
                "extra": extra or {},
            }
            self.dir.mkdir(parents=True, exist_ok=True)
            nbytes = tensor_bytes(state)
            self._make_room(step, nbytes)
            tmp = self.dir / f".tmp-step-{step:06d}-{os.getpid()}"
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.mkdir()
            try:
                torch.save(state, tmp / "state.pt")
                (tmp / "meta.json").write_text(json.dumps({"step": step, "data": data_state or {}}))
            except Exception as e:
                full = out_of_disk(e, tmp, nbytes)
                shutil.rmtree(tmp, ignore_errors=True)
                if not full:
                    raise
                raise TrainingError(f"the disk filled while writing the checkpoint of step {step} in {self.dir} "
                                    f"({_newest(self.all())}; its temp dir removed)") from e
            if final.exists():
                shutil.rmtree(final)
            os.replace(tmp, final)  # atomic: a checkpoint dir either exists whole or not at all
            for old in self.all()[:-self.keep] if self.keep > 0 else []:
                shutil.rmtree(old, ignore_errors=True)
        if self.accelerator is not None:
            self.accelerator.wait_for_everyone()
        return final

    def _make_room(self, step: int, nbytes: int) -> None:
        """Room on disk for a checkpoint of `nbytes` (plus 1%): when short, first drop the checkpoints this save
        would drop once written (the oldest beyond keep - 1; never the newest, so a failed write still leaves
        one), then, still short, a TrainingError naming what it takes and what is free."""
        need = int(nbytes * 1.01) + 2**20
        if shutil.disk_usage(self.dir).free >= need:
            return
        ckpts = self.all()
        stale = ckpts[:-1][:max(0, len(ckpts) - (self.keep - 1))] if self.keep > 0 else []
        for old in stale:
            shutil.rmtree(old, ignore_errors=True)
        free = shutil.disk_usage(self.dir).free
        if free < need:
            raise TrainingError(f"not enough disk for the checkpoint of step {step}: it takes {need / 2**20:,.1f} "
                                f"MiB and {self.dir} has {free / 2**20:,.1f} MiB free ({_newest(self.all())}); "
                                f"free some space, or lower keep_checkpoints, then resume=true")

    def all(self) -> list[Path]:
        if not self.dir.is_dir():
            return []
        return sorted(p for p in self.dir.glob("step-*") if (p / "state.pt").is_file())

    def latest(self) -> Path | None:
        ckpts = self.all()
        return ckpts[-1] if ckpts else None

    def load(self, path: Path, model, optimizer=None, scheduler=None) -> dict[str, Any]:
        """Restore states in place; returns {'step', 'data', 'extra'}."""
        state = torch.load(Path(path) / "state.pt", map_location="cpu", weights_only=False)
        target = self.accelerator.unwrap_model(model) if self.accelerator is not None else model
        target.load_state_dict(state["model"])
        if optimizer is not None and state["optimizer"] is not None:
            optimizer.load_state_dict(state["optimizer"])
        if scheduler is not None and state["scheduler"] is not None:
            scheduler.load_state_dict(state["scheduler"])
        _set_rng_state(state["rng"])
        return {"step": state["step"], "data": state["data"], "extra": state["extra"]}


def resume_run(ckpt: Checkpointer, metrics: "MetricsLog", model, optimizer=None, scheduler=None, *, resume: bool,
               say: Callable[[str], None] = print, tag: str = "", unit: str = "step") -> dict[str, Any]:
    """With resume=true: restore the newest checkpoint into model / optimizer / scheduler (and the RNG states) in
    place and drop the metrics rows logged after it. Returns {"step", "data", "extra"}: step 0 and nothing
    else when starting fresh or when there is no checkpoint yet (said so)."""
    fresh: dict[str, Any] = {"step": 0, "data": {}, "extra": {}}
    if not resume:
        return fresh
    last = ckpt.latest()
    if last is None:
        say(f"[{tag}] resume=true but no checkpoint in {ckpt.dir}; starting from {unit} 0")
        return fresh
    state = ckpt.load(last, model, optimizer, scheduler)
    metrics.truncate_after(state["step"])
    say(f"[{tag}] resumed from {last} at {unit} {state['step']}")
    return state


def prepare_run_dir(run_dir: Path, resume: bool, log: Callable[[str], None] = print) -> None:
    """Make the run dir. Starting fresh over an earlier run keeps it as `<dir>.prev` (nothing is lost)."""
    run_dir = Path(run_dir)
    if run_dir.exists() and not resume and any(run_dir.iterdir()):
        prev = run_dir.with_name(run_dir.name + ".prev")
        if prev.exists():
            shutil.rmtree(prev)
        run_dir.rename(prev)
        log(f"[posttrain] an earlier run in {run_dir} was moved to {prev} (pass resume=true to continue it instead)")
    run_dir.mkdir(parents=True, exist_ok=True)


def write_json(path: Path, obj: Any) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str))
    tmp.replace(path)


def iter_jsonl(path: Path) -> Iterable[dict]:
    with open(path) as f:
        for line in f:
            if line.strip():
                yield json.loads(line)
