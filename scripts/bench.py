"""Benchmarks, measured side by side in one run and reported as ratios (never timed assertions in tests).

Sections (`--only NAME`, repeatable; all of them by default, in this order):
  generate  the rollout engine (`posttrain.rollout.generate`) against `model.generate` on the same
            random-init preset, prompts (16-48 tokens, mixed), settings (sampling at temperature 1, no
            top-k / top-p) and seed; both produce exactly max_new_tokens per row (`min_new_tokens` for
            generate, `ignore_eos=True` for the engine). Warm-up excluded, runs alternate, medians.
  sft       our SFT step (data.tokenize_completions / collate_completions, logprobs.nll_sum, loop.optimizer_step)
            against TRL's SFTTrainer on the same tiny model and tiny-summarize rows, given to TRL as our own
            token ids (input_ids + completion_mask, so both see identical tokens), batch 16, lr 1e-4
            constant, clipping 1.0, max length 256, completion-only loss, same batch order (TRL's sampler
            "sequential"), no packing / padding-free on either side; tokens/s (non-pad tokens) and ratio.
  rm        our reward-model step (scoring.pair_rewards + losses.bradley_terry_loss) against
            TRL's RewardTrainer on the same tiny reward model (the tiny LM under a seeded one-output head,
            `models.load_reward_init`), the same pairs as our token ids (chosen_ids / rejected_ids), batch 16, lr
            1e-4 constant, same order; chosen and rejected in one forward on both sides; pairs/s and ratio.
  dpo       our DPO training loop (preferences.pair_logps / reference_logps, losses.dpo_loss with
            loop.optimizer_step) against TRL's DPOTrainer on the same tiny model, tiny-summarize pairs,
            batch (8), lr and beta, same order; tokens/s of the same pairs, reference log-probs included.
  ppo       a PPO iteration of `posttrain ppo` (the trainer, through the CLI) on tiny-summarize with a
            random-init tiny policy and reward model, split into rollout / scoring / the rest (old, reference
            and value forwards, GAE, ppo_epochs x minibatch updates). TRL has no PPO trainer to compare with
            in the installed version (it was moved to trl.experimental.ppo in TRL 1.10, huggingface/trl#4482,
            and deleted, huggingface/trl#7020), so this section prints our numbers and no ratio; if a TRL
            PPOTrainer is importable it says so (a comparison would need its own driver).
  grpo      a GRPO step of `posttrain grpo` (the trainer, through the CLI) against TRL's GRPOTrainer on the
            same random-init tiny model, prompts, 2 prompts x 8 completions x <= 64 tokens, reward (length
            verifier), beta 0, one pass; s/step. Then the same with GSPO on both sides (policy_loss=gspo;
            TRL's importance_sampling_level="sequence", loss_type="grpo"; the paper's clip ranges 3e-4 / 4e-4).
  distill   an on-policy distillation step of `posttrain distill` (the trainer, through the CLI) against TRL's
            DistillationTrainer: random-init tiny student, small teacher (same tokenizer), 16 prompts x 1
            completion x <= 64 tokens, reverse KL over the vocabulary (TRL beta 1.0); s/step.
  real      a real instruct model (--real DIR, default models/smollm2-135m-instruct; skipped when missing): the
            engine with fp32 and with bf16 weights (rollout.dtype) against fp32 `model.generate` at batch 1 / 16 /
            32 (word-math prompts through the chat template, T=1, exactly max_new_tokens), and one training step
            (HF forward + backward + AdamW, batch 8) fp32 against bf16 autocast, and the policy update's log-prob
            forward + backward (8 rows x 124 tokens) on the lean training forward and the HF one, each fp32 and
            under bf16 autocast; then one SFT, RM, DPO and GRPO step of ours against TRL's on it (word-math rows
            through the chat template; SFT batch 4 and 16 rows (~1.1k tokens), RM 8 pairs (a seeded one-output head
            on the model; TRL's RewardTrainer), DPO 4 pairs, GRPO 2 prompts x
            4 x <= 64 tokens, lr 1e-7 so that neither side's completions shrink under the length reward during
            the run; each side's mean completion length is printed), each fp32 and with bf16 on both sides (ours
            run.mixed_precision=bf16, GRPO also rollout.dtype=bfloat16; TRL bf16=True); then one multi-turn GRPO
            step with the calculator, as the tools section does but on the real model: a short LoRA SFT on word-calc's
            tool-use demonstrations first (untimed, ~1 min), calc-words on word-calc's held-out problems, 2 prompts x
            8 episodes, <= 3 turns x 64 tokens, <= 256 in all, both sides with CHATML_TOOL_TEMPLATE (SmolLM2's ChatML
            plus `tool_calls`), fp32 and bf16. First it measures this machine's limits in the run (matmul rate fp32
            and bf16 at 2048^3; weight streaming, stream_gbs) and prints each engine row's weight bandwidth and
            FLOP/s (generation_flops) and each training row's FLOP/s (6N, token_flops) as fractions of them. --real-parts picks parts (engine, step,
            trainers, tools). --quick: 8 + 12 min measured (engine, step and trainers; tools). The bf16
            rows run where bf16 is native and faster (`--real-bf16 auto`, the default: what run.mixed_precision=auto
            decides); on other CPUs bf16 is emulated, 2-5x slower than fp32, and `--real-bf16 yes` forces them.
  microbatch micro-batches of rows of like length (`data.token_groups(by_length=True)`, what every trainer's
            micro-batching does) against consecutive ones (what it did before), ours against ours on the same rows,
            random-init `small` model, optimizer and budget (--micro-tokens padded tokens per micro-batch, default
            1024): an SFT step (`data.token_groups` as `posttrain sft` calls it, `logprobs.nll_sum`,
            `loop.optimizer_step`; 16 rows of 32-512 tokens, log-uniform) and a policy update
            (`sharding.micro_batches`, `logprobs.sequence_logprobs` forward + backward, AdamW; 2 prompts of 40-80
            tokens x 8 completions of 8-256, left-padded prompts); synthetic token ids, lengths drawn so that a few
            long rows dominate, as in chat data (rows of even length, e.g. tiny-summarize's 33-85 tokens, gain
            nothing). Padded tokens, micro-batches per step, s/step and the ratio. No TRL side: TRL's micro-batches
            are its per-device batches, a fixed number of consecutive rows each padded to its longest
            (`group_by_length` orders the whole dataset instead).
  multiturn multi-turn episodes with a tool (posttrain.rollout.multiturn; a random tiny chat model whose turns end
            at eos after a few tokens, every turn answered by the calculator, <= 4 turns) against single-turn
            rollouts of the same number of sampled tokens (ignore_eos) at each batch size; the time ratio next to
            the ratio of decoding steps, (sampled + environment tokens) / sampled, and the tools' seconds. Ours
            only (TRL's tool-calling GRPO: the tools section).
  tools     one multi-turn GRPO step in the calc environment: `posttrain grpo` with grpo.env=calc (the trainer, through
            the CLI) against TRL's GRPOTrainer with the calculator as a tool (`tools=[calculator]`,
            max_tool_calling_iterations, its tool-calling loop on transformers' generate), on the tiny chat model
            after a short SFT on tiny-calc's tool-use demonstrations (--tools-sft-steps, untimed; a random model never
            writes a call), same 64 problems, same prompt token ids (asserted), 2 prompts x 8 episodes, <= 3 turns x 48
            tokens, <= 192 tokens in all, the calc reward; s/step, ratio, each side's turns / calls / sampled and tool
            tokens per episode, a per-token ratio, and what the two APIs do not let us make equal. TRL needs a chat
            template that renders `tool_calls` and a response parser: both sides get TOOL_CHAT_TEMPLATE (the preset's
            template plus tool_calls in the calc call format), TRL's tokenizer a response_template. If TRL refuses to
            run, the section prints why (exception and the TRL line) instead of a ratio. No memory probe.
  scaling   how cost grows with model size (--presets, default tiny and small) and sequence length: the
            rollout engine (batch 16, 32-token prompts, 64/128/256 new tokens; 64/128 with --quick) and a
            training step (forward + backward + AdamW on batch 8 of 64/128/256 tokens), tokens/s, time
            relative to the shortest length and to the first preset, achieved GFLOP/s against this machine's
            measured fp32 matmul rate. Ours only (no TRL counterpart).
Every TRL comparison: TRL (optional: `pip install -e '.[bench]'`) configured for this CPU (fp32: bf16=False,
activation (gradient) checkpointing off, asserted after each run; no logging / saving / eval), each side's
own AdamW implementation; TRL's time runs from its first step (a TrainerCallback) to the end of `train()`, and
ours from just before our first step (building our optimizer, a few ms, included), so TRL's one-off setup
inside `train()` is not charged to it; each implementation runs once untimed
first (warm-up), then runs alternate,
medians (ppo and grpo: the first iteration(s) of every run are the warm-up). Both run in the same process,
so posttrain's glibc malloc tuning (`loop.setup`) applies to TRL's timed runs too. sft and rm also check
that TRL trained on exactly our non-pad token count.

Peak memory (every section but scaling and tools; --no-memory skips it): each implementation runs its timed workload
(generate: the first preset at the largest batch; dpo --quick: TRL's default live-reference variant only)
once more in a FRESH Python process (`--memory-probe SECTION:IMPL`, started by the section), after the
section's shared setup (imports, tokenizer, data, base model). We record the process's resident set just
before the run, reset the kernel's peak-RSS mark (`/proc/self/clear_refs` <- 5) and read the peak
(`VmHWM`) after it: peak RSS above the pre-run baseline, in MiB, i.e. everything the implementation
allocates (its model copies, reference, optimizer state, activations, caches), which tracemalloc cannot see
(torch allocates outside Python's allocator). A fresh process per implementation because freed memory
stays in the allocator (posttrain raises glibc's trim threshold) and would hide the second one's growth.
Linux only (elsewhere the probe says so and reports nothing); host memory only (with --device cuda, GPU
memory is not counted).

CPU:       python scripts/bench.py --quick            (all sections, every ratio; < 3 min on 2 idle cores)
           python scripts/bench.py --only sft --only rm --threads 2 --json runs/bench.json
           python scripts/bench.py --only scaling --presets tiny,small,base
           python scripts/bench.py --only tools --threads 2 --json runs/bench-tools.json
                                                      (~4 min on 2 idle cores, estimated)
Multi-GPU: not applicable (single-process microbenchmarks; `--device cuda` runs generate and scaling on one GPU).
Runtime:   --quick: 4 min 46 s measured single-threaded on a loaded 2-core machine (load average 3-3.5, 3 min
           15 s of CPU), memory probes included; about 2 min expected on 2 idle cores (not yet measured
           there). Full: roughly 3x the quick run. Both before the tools section, which adds ~1.5 min (--quick) to
           ~4 min (full) on 2 idle cores, about 1 min of it the untimed SFT (estimates, not measured there).

Achieved GFLOP/s counts the same useful work for both implementations:
  generation FLOPs = 2*N_block*(sum_prompt_tokens + B*(M-1)) + 2*N_head*B*M + 4*L*H*Dh*(attended key positions)
with N_block the parameters of the transformer blocks, N_head = d_model*V (the logits matmul, run once
per sampled token), M new tokens per row, and attended positions summed over every fed token (a prompt
token at position i attends to i+1 keys, the t-th new token to prompt_len+t).
  training FLOPs = 6*N_block*B*T + 6*N_head*B*(T-1) + 12*L*H*Dh*B*T(T+1)/2
for a forward + backward over B rows of T tokens (the "6N" rule: 2 FLOPs per parameter per token forward,
4 backward; logits only at the T-1 positions that have a target; causal attention's QK^T and AV, 4*Dh FLOPs
per query-key pair per head forward, x3 with backward). Norms, activations, softmax and the AdamW update
(~10 FLOPs per parameter per step) are left out, so the figures slightly understate the work. The
reference is the machine's fp32 matmul rate: a large torch.matmul on the same threads, timed at the start of
generate and of scaling (best of 10), the best rate seen in the run.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import gc
import io
import json
import os
import platform
import random
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from posttrain.models import PRESETS, build_model, count_parameters, train_tokenizer  # noqa: E402
from posttrain.rollout import generate, select_backend  # noqa: E402


# ------------------------------------------------------------------ shared helpers


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def matmul_gflops(n: int, repeats: int, device: str = "cpu", dtype: torch.dtype = torch.float32) -> float:
    a = torch.randn(n, n, device=device).to(dtype)
    b = torch.randn(n, n, device=device).to(dtype)
    for _ in range(2):
        a @ b
    times = []
    for _ in range(repeats):
        if device != "cpu":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        a @ b
        if device != "cpu":
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return 2 * n ** 3 / min(times) / 1e9


def matmul_peak(args) -> float:
    """The fp32 matmul rate on this run's threads: measured at each call (each section that reports a % of it),
    the best rate seen so far in this run returned (a probe slowed by other load must not inflate the %)."""
    n = 1024 if args.quick else 2048
    now = matmul_gflops(n, 10, args.device)
    args.matmul_peak = max(now, getattr(args, "matmul_peak", None) or 0.0)
    print(f"fp32 matmul rate ({n}^3, {torch.get_num_threads()} threads): {now:.0f} GFLOP/s now, "
          f"{args.matmul_peak:.0f} GFLOP/s best this run (the reference for '% of matmul')")
    return args.matmul_peak


def stream_gbs(repeats: int, device: str = "cpu", dtype: torch.dtype = torch.float32, rows: int = 16) -> float:
    """Weight-streaming bandwidth: a batch of `rows` vectors through a 16384 x 4096 matrix (256 MB in fp32, 128 MB
    in bf16; far past the caches), as a decode step streams its weights, or a sum over it when that reads faster;
    GB/s of the matrix's bytes, best of `repeats`."""
    w = torch.randn(16384, 4096, device=device).to(dtype)
    x = torch.randn(rows, 4096, device=device).to(dtype)
    for _ in range(2):
        x @ w.T
        w.sum()
    # the faster of the matmul and a plain reduction over the same bytes: what streaming the matrix can reach here
    best = min(min(_timed(lambda: x @ w.T, device), _timed(w.sum, device)) for _ in range(repeats))
    return w.numel() * w.element_size() / best / 1e9


def real_limits(args) -> dict:
    """This machine's limits on this run's threads, measured in the same run as the stages they are compared with:
    the matmul rate (2048^3, fp32 and, with the bf16 rows, bf16) and the weight-streaming bandwidth (stream_gbs)."""
    n = 2048  # ~1 s in all; a smaller matrix understates the rate
    dtypes = {"fp32": torch.float32, **({"bf16": torch.bfloat16} if args.bf16_rows else {})}
    out = {p: {"matmul_gflops": matmul_gflops(n, 10, args.device, d), "stream_gbs": stream_gbs(10, args.device, d)}
           for p, d in dtypes.items()}
    print("limits measured here: " + "; ".join(f"{p} matmul {v['matmul_gflops']:.0f} GFLOP/s ({n}^3), weight stream "
                                              f"{v['stream_gbs']:.1f} GB/s (16 x 4096 through 16384 x 4096)"
                                              for p, v in out.items()))
    return out


def token_flops(model, tokens: float, head_tokens: float | None = None, passes: float = 3.0) -> float:
    """2 * N * tokens * passes: the "6N" rule with passes=3 (forward + backward), 1 for a forward alone. The blocks
    run at every token; the output head (d x V) at `head_tokens` (the positions whose log-prob is needed; default
    every token). Attention's quadratic term is left out (rows of ~100-300 tokens: a few % of the work), so the
    fractions slightly understate the work done; so does a side that runs the head at more positions than needed."""
    cfg = model.config
    n_block = sum(p.numel() for p in model.model.layers.parameters())
    head = cfg.hidden_size * cfg.vocab_size * (tokens if head_tokens is None else head_tokens)
    return 2.0 * (n_block * tokens + head) * passes


def _of_peak(flops: float, seconds: float, limits: dict, precision: str) -> str:
    rate = flops / seconds / 1e9
    return f"{rate:.0f} GFLOP/s, {100 * rate / limits[precision]['matmul_gflops']:.0f}% of the {precision} matmul rate"


def _sync(device: str) -> None:
    if device != "cpu":
        torch.cuda.synchronize()


def _timed(fn, device: str) -> float:
    _sync(device)
    t0 = time.perf_counter()
    fn()
    _sync(device)
    return time.perf_counter() - t0


def _corpus(n: int, seed: int = 0) -> list[str]:
    rng = random.Random(seed)
    words = ("the a model reward policy token batch sample value gradient loss step update prompt answer "
             "number five seven eleven plus minus equals because therefore summary short long text").split()
    return [" ".join(rng.choice(words) for _ in range(rng.randint(40, 80))) for _ in range(n)]


def generation_flops(model, prompt_lens: list[int], new_tokens: int) -> float:
    cfg = model.config
    L, d, V = cfg.num_hidden_layers, cfg.hidden_size, cfg.vocab_size
    H = cfg.num_attention_heads
    Dh = getattr(cfg, "head_dim", None) or d // H
    n_block = sum(p.numel() for p in model.model.layers.parameters())
    B, M = len(prompt_lens), new_tokens
    fed = sum(prompt_lens) + B * (M - 1)
    attended = sum(p * (p + 1) // 2 + sum(p + t for t in range(1, M)) for p in prompt_lens)
    return 2 * n_block * fed + 2 * d * V * B * M + 4 * L * H * Dh * attended


def training_flops(model, batch: int, seq_len: int) -> float:
    """Forward + backward FLOPs of a causal-LM loss over `batch` unpadded rows of `seq_len` tokens (see the
    module docstring): 6*N_block*tokens + 6*d*V*(positions with a target) + 12*L*H*Dh*(causal query-key pairs)."""
    cfg = model.config
    L, d, V = cfg.num_hidden_layers, cfg.hidden_size, cfg.vocab_size
    H = cfg.num_attention_heads
    Dh = getattr(cfg, "head_dim", None) or d // H
    n_block = sum(p.numel() for p in model.model.layers.parameters())
    B, T = batch, seq_len
    return 6 * n_block * B * T + 6 * d * V * B * (T - 1) + 12 * L * H * Dh * B * T * (T + 1) // 2


def _alternate(runners: dict, repeats: int, device: str) -> dict[str, list[float]]:
    """Each runner (returning its own elapsed seconds) once untimed (warm-up), then `repeats` alternating rounds."""
    for fn in runners.values():
        fn()
    times: dict[str, list[float]] = {k: [] for k in runners}
    for _ in range(repeats):  # alternate the implementations so drifting load hits both
        for k, fn in runners.items():
            _sync(device)
            times[k].append(fn())
    return times


@functools.lru_cache(maxsize=None)
def _summarize_tokenizer():
    from posttrain.config import TaskConfig
    from posttrain.tasks import tokenizer_corpus

    return train_tokenizer(tokenizer_corpus(TaskConfig(name="tiny-summarize", n_train=2000)), vocab_size=1024)


def _summarize_pairs(n: int, seed: int = 0) -> list[dict]:
    """n preference rows from the tiny-summarize generator: chosen = the reference summary, rejected =
    another document's summary (realistic lengths; the labels do not matter for throughput)."""
    from posttrain.tasks import get_task

    ex = get_task("tiny-summarize").make_examples(n + 1, seed, "train")
    return [{"prompt": ex[i]["prompt"], "chosen": ex[i]["completion"], "rejected": ex[i + 1]["completion"],
             "_row": i + 1} for i in range(n)]


def _trl_quiet():
    """Silence TRL / transformers / datasets chatter; returns PrinterCallback (removed from every trainer)."""
    import datasets
    from transformers import logging as hf_logging
    from transformers.trainer_callback import PrinterCallback

    hf_logging.set_verbosity_error()
    datasets.disable_progress_bars()
    return PrinterCallback


def _no_checkpointing() -> dict:
    """Activation (gradient) checkpointing off, TRL's default on: by its current name when transformers has it."""
    import dataclasses

    from transformers import TrainingArguments

    names = {f.name for f in dataclasses.fields(TrainingArguments)}
    return {"activation_checkpointing" if "activation_checkpointing" in names else "gradient_checkpointing": False}


def _trl_common(args, tmp: str, batch: int, bf16: bool = False) -> dict:
    """TrainingArguments shared by every TRL trainer here: fp32 (or bf16 autocast over fp32 weights, bf16=True), no
    checkpointing, no logging / saving / eval, our batch order (sequential sampler), one pass."""
    return dict(output_dir=tmp, per_device_train_batch_size=batch, num_train_epochs=1,
                lr_scheduler_type="constant", max_grad_norm=1.0, bf16=bf16, fp16=False,
                **_no_checkpointing(), use_cpu=args.device == "cpu", logging_strategy="no",
                save_strategy="no", eval_strategy="no", report_to=[], disable_tqdm=True,
                dataloader_num_workers=0, seed=0, train_sampling_strategy="sequential")


def _step_timer(device: str, metric: str | None = None):
    """A TrainerCallback that times each of a TRL trainer's steps from on_step_begin to on_step_end (online trainers
    generate inside the step), after a device sync. With `metric`, it also reads that step's value of one of TRL's
    logged metrics from the trainer's metric store (set `.trainer` once the trainer exists; TRL clears the store
    whenever it logs, so it is read at every step end); a step without it records nan."""
    from transformers import TrainerCallback

    class StepTimer(TrainerCallback):
        def __init__(self):
            self.times, self.values, self.t0, self.trainer = [], [], 0.0, None

        def on_step_begin(self, *a, **k):
            self.t0 = time.perf_counter()

        def on_step_end(self, *a, **k):
            _sync(device)
            self.times.append(time.perf_counter() - self.t0)
            if metric is not None:
                m = getattr(self.trainer, "_metrics", {}).get("train", {}).get(metric)
                self.values.append(m[-1] if m else float("nan"))

    return StepTimer()


def _cli_step_times(metrics_file: Path, phases: tuple[str, ...]) -> tuple[list[float], dict[str, float]]:
    """Seconds per step of a run of one of our trainers through the CLI, from its metrics.jsonl (time/step:
    sampling, scoring and update), the first 2 steps (warm-up) left out, and the median of each phase's time/<phase>
    plus the mean completion length of the remaining steps."""
    rows = [json.loads(l) for l in Path(metrics_file).read_text().splitlines()]
    rows = [r for r in rows if "time/step" in r][2:]
    medians = {k: statistics.median(r[f"time/{k}"] for r in rows) for k in phases}
    medians["completion_tokens"] = statistics.mean(r["completion/length"] for r in rows)
    return [r["time/step"] for r in rows], medians


def _trl_missing(e: Exception) -> None:
    print(f"TRL not installed ({e}); `pip install -e '.[bench]'` to compare. Ours alone:")


# ------------------------------------------------------------------ peak memory (fresh process per implementation)

PROBE_MARK = "BENCH-MEMORY "


def _status_mib(key: str) -> float:
    m = re.search(rf"^{key}:\s+(\d+) kB", Path("/proc/self/status").read_text(), re.M)
    return int(m.group(1)) / 1024


def _memory_probe(spec: str, args) -> int:
    """Child side of `peak_memory`: set up SECTION, run IMPL's workload once, print its peak RSS above baseline."""
    section, _, impl = spec.partition(":")
    if not (Path("/proc/self/status").is_file() and Path("/proc/self/clear_refs").exists()):
        print(PROBE_MARK + json.dumps({"error": "peak RSS needs Linux /proc (VmHWM, clear_refs)"}))
        return 0
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        ctx = SETUPS[section](args)
        run = ctx.runners[impl]
        gc.collect()
        baseline = _status_mib("VmRSS")
        Path("/proc/self/clear_refs").write_text("5")  # reset the peak-RSS mark (VmHWM) to the current RSS
        run()
        peak = _status_mib("VmHWM")
        if hasattr(ctx, "cleanup"):
            ctx.cleanup()
    print(PROBE_MARK + json.dumps({"baseline_mib": baseline, "peak_mib": peak, "delta_mib": peak - baseline}))
    return 0


def peak_memory(section: str, impls: list[str], args) -> dict[str, dict]:
    """Peak RSS above the pre-run baseline of each implementation, each in a fresh process (module docstring)."""
    if args.no_memory:
        return {}
    out = {}
    for impl in impls:
        cmd = [sys.executable, str(Path(__file__).resolve()), *args.argv, "--memory-probe", f"{section}:{impl}"]
        p = subprocess.run(cmd, capture_output=True, text=True)
        lines = [l for l in p.stdout.splitlines() if l.startswith(PROBE_MARK)]
        if p.returncode or not lines:
            tail = (p.stderr.strip().splitlines() or ["no output"])[-1]
            out[impl] = {"error": f"probe failed (exit {p.returncode}): {tail}"}
        else:
            out[impl] = json.loads(lines[-1][len(PROBE_MARK):])
    return out


def print_memory(mem: dict[str, dict], labels: dict[str, str], ref: str = "posttrain") -> None:
    if not mem:
        return
    base = mem.get(ref, {}).get("delta_mib")
    print("peak memory, fresh process each (peak RSS above the RSS just before the run"
          + (f"; ratio = it / {labels.get(ref, ref)}'s):" if base and len(mem) > 1 else "):"))
    for impl, m in mem.items():
        if "error" in m:
            print(f"  {labels.get(impl, impl):<52} n/a ({m['error']})")
            continue
        ratio = f"{m['delta_mib'] / base:>6.2f}x" if base and impl != ref else ""
        print(f"  {labels.get(impl, impl):<52} {m['delta_mib']:>7.0f} MiB {ratio}  (baseline {m['baseline_mib']:.0f} MiB)")


# ------------------------------------------------------------------ section: generate


def _generate_setup(args) -> SimpleNamespace:
    """Memory-probe workload of the generate section: the first preset at the largest batch."""
    corpus = _corpus(300)
    tok = train_tokenizer(corpus, vocab_size=1024)
    enc = [tok(c)["input_ids"] for c in corpus]
    rng = random.Random(1)
    B, M = max(args.batches), args.max_new_tokens
    model = build_model(args.presets[0], tok, seed=0).to(args.device).eval()
    prompts = [enc[i % len(enc)][:rng.randint(16, 48)] for i in range(B)]
    batch = tok.pad({"input_ids": prompts}, return_tensors="pt").to(args.device)

    def hf():
        torch.manual_seed(0)
        with torch.inference_mode():
            model.generate(**batch, do_sample=True, temperature=1.0, top_k=0, top_p=1.0, max_new_tokens=M,
                           min_new_tokens=M, pad_token_id=tok.pad_token_id, eos_token_id=tok.eos_token_id)

    def engine():
        generate(model, tok, prompts, max_new_tokens=M, temperature=1.0, ignore_eos=True, seed=0)

    return SimpleNamespace(runners={"model.generate": hf, "engine": engine})


def bench_generate(args) -> dict:
    device = args.device
    presets = args.presets
    batches = args.batches
    M = args.max_new_tokens
    repeats = args.repeats
    peak = matmul_peak(args)
    corpus = _corpus(300)
    tok = train_tokenizer(corpus, vocab_size=1024)
    enc = [tok(c)["input_ids"] for c in corpus]
    rng = random.Random(1)
    rows_out = []
    header = (f"{'preset':<6} {'batch':>5} {'generate tok/s':>15} {'engine tok/s':>13} {'ratio':>7} "
              f"{'generate GFLOP/s':>17} {'engine GFLOP/s':>15} {'% of matmul':>11}")
    for preset in presets:
        model = build_model(preset, tok, seed=0).to(device).eval()
        fwd, why = select_backend(model, 48 + M)
        print(f"\n{preset}: {count_parameters(model) / 1e6:.2f}M parameters; engine path: {why}")
        print(header)
        for B in batches:
            lens = [rng.randint(16, 48) for _ in range(B)]
            prompts = [enc[i % len(enc)][:n] for i, n in enumerate(lens)]
            batch = tok.pad({"input_ids": prompts}, return_tensors="pt").to(device)

            def hf(seed=0):
                torch.manual_seed(seed)
                with torch.inference_mode():
                    return model.generate(**batch, do_sample=True, temperature=1.0, top_k=0, top_p=1.0,
                                          max_new_tokens=M, min_new_tokens=M, pad_token_id=tok.pad_token_id,
                                          eos_token_id=tok.eos_token_id)

            def engine(seed=0):
                return generate(model, tok, prompts, max_new_tokens=M, temperature=1.0, ignore_eos=True,
                                seed=seed)

            out_hf = hf()  # warm-up (excluded) and token-count check
            out_en = engine()
            assert out_hf.shape[1] - batch["input_ids"].shape[1] == M
            assert sum(len(r.completion_ids) for r in out_en) == B * M
            t_hf, t_en = [], []
            for r in range(repeats):  # alternate the implementations so drifting load hits both
                t_hf.append(_timed(lambda: hf(r), device))
                t_en.append(_timed(lambda: engine(r), device))
            med_hf, med_en = statistics.median(t_hf), statistics.median(t_en)
            flops = generation_flops(model, lens, M)
            row = dict(preset=preset, batch=B, new_tokens=M, hf_tok_s=B * M / med_hf, engine_tok_s=B * M / med_en,
                       ratio=med_hf / med_en, engine_gflops=flops / med_en / 1e9, hf_gflops=flops / med_hf / 1e9,
                       hf_times=t_hf, engine_times=t_en)
            row["engine_pct_of_matmul"] = 100 * row["engine_gflops"] / peak
            rows_out.append(row)
            print(f"{preset:<6} {B:>5} {row['hf_tok_s']:>15.0f} {row['engine_tok_s']:>13.0f} {row['ratio']:>6.2f}x "
                  f"{row['hf_gflops']:>17.1f} {row['engine_gflops']:>15.1f} {row['engine_pct_of_matmul']:>10.1f}%",
                  flush=True)
    print("\nratio = generate time / engine time (medians of alternating runs).")
    print(f"memory workload: {presets[0]}, batch {max(batches)}, {M} new tokens")
    mem = peak_memory("generate", ["model.generate", "engine"], args)
    print_memory(mem, {"model.generate": "model.generate", "engine": "posttrain rollout engine"}, ref="engine")
    return dict(matmul_gflops=peak, rows=rows_out, memory=mem)


# ------------------------------------------------------------------ section: sft


_REAL: dict = {}


def _real_base(args):
    """(tokenizer, fp32 model) of the real model directory --real, loaded once; its chat template configured as the
    CLI does (chat.configure "auto"), so our prompt encoders render every prompt through it."""
    if args.real not in _REAL:
        from posttrain import chat
        from posttrain.models import load_model, load_tokenizer

        tok = load_tokenizer(args.real)
        chat.configure(tok, "auto", say=lambda _: None)
        _REAL[args.real] = (tok, load_model(args.real).to(args.device).eval())
    return _REAL[args.real]


def _first_step_clock():
    """A TrainerCallback that notes when TRL's first step begins: TRL's time runs from there to the end of
    `train()`, so its one-off setup inside `train()` (dataloader, optimizer, accelerate preparation) is not
    charged to it, as ours starts at our first step."""
    from transformers import TrainerCallback

    class FirstStepClock(TrainerCallback):
        t0: float | None = None

        def on_step_begin(self, *a, **k):
            if self.t0 is None:
                self.t0 = time.perf_counter()

    return FirstStepClock()


def _trl_timed_train(make_trainer, printer, steps: int, tokens: int, args) -> float:
    """Build a TRL trainer (quietly), train it, and return the seconds from its first step to the end of `train()`;
    checks that it ran `steps` steps without activation checkpointing on exactly our `tokens` non-pad tokens (when
    it counts them)."""
    with contextlib.redirect_stderr(io.StringIO()):
        trainer = make_trainer()
        trainer.remove_callback(printer)
        clock = _first_step_clock()
        trainer.add_callback(clock)
        out = trainer.train()
    _sync(args.device)
    dt = time.perf_counter() - clock.t0
    assert out.global_step == steps, f"TRL ran {out.global_step} steps, expected {steps}"
    assert not trainer.args.gradient_checkpointing, "TRL ran with activation checkpointing"
    seen = getattr(trainer, "_total_train_tokens", tokens)
    assert seen == tokens, f"TRL trained on {seen} non-pad tokens, we on {tokens}"
    return dt


def _sft_setup(args, real: bool = False, bf16: bool = False, rows: int = 4) -> SimpleNamespace:
    """Our SFT step and TRL's SFTTrainer over the same S*B rows (see the module docstring): tiny-summarize on the
    tiny model, or (real=True) word-math rows through the chat template on the real model (--real), batch `rows`.
    bf16: both under bf16 autocast over fp32 weights (ours run.mixed_precision=bf16, TRL bf16=True)."""
    from posttrain import loop
    from posttrain.tasks import get_task
    from posttrain.data import collate_completions, tokenize_completions
    from posttrain.logprobs import nll_sum

    if real:
        tok, base = _real_base(args)
        B, S, lr, max_len = rows, 2 if args.quick else 3, 1e-5, 512
        data_rows = get_task("word-math").make_examples(S * B, 0, "train")
    else:
        B, S, lr, max_len = 16, 6 if args.quick else 16, 1e-4, 256
        tok = _summarize_tokenizer()
        data_rows = get_task("tiny-summarize").make_examples(S * B, 0, "train")
        base = build_model("tiny", tok, seed=0).to(args.device)
    pairs, dropped = tokenize_completions(data_rows, tok, max_len)
    assert not dropped and len(pairs) == S * B
    tokens = sum(len(p) + len(c) for p, c in pairs)  # non-pad tokens through the model
    loss_tokens = sum(len(c) for _, c in pairs)  # completion tokens (eos included): the loss's tokens
    pad = tok.pad_token_id

    def ours() -> float:
        model = copy.deepcopy(base)
        accelerator = loop.setup(0, mixed_precision="bf16" if bf16 else None)
        t0 = time.perf_counter()
        optimizer = loop.build_optimizer(model, lr)
        model, optimizer = accelerator.prepare(model, optimizer)  # as the trainer does (its autocast under bf16)
        scheduler = loop.build_scheduler(optimizer, 0, S, "constant")
        for step in range(S):
            batch = collate_completions(pairs[step * B:(step + 1) * B], pad)
            n = float(batch["completion_mask"].sum())

            def loss_fn(mb):
                s, _ = nll_sum(model, mb)
                return s / n, {}

            loop.optimizer_step(accelerator, model, optimizer, scheduler, [batch], loss_fn, 1.0, step + 1)
        _sync(args.device)
        return time.perf_counter() - t0

    ctx = SimpleNamespace(B=B, S=S, lr=lr, max_len=max_len, tokens=tokens, loss_tokens=loss_tokens, base=base,
                          runners={"posttrain": ours}, trl_error=None)
    try:
        from datasets import Dataset
        from trl import SFTConfig as TRLConfig, SFTTrainer
    except ImportError as e:
        ctx.trl_error = e
        return ctx
    printer = _trl_quiet()
    data = [{"input_ids": p + c, "completion_mask": [0] * len(p) + [1] * len(c)} for p, c in pairs]
    tmp = tempfile.mkdtemp(prefix="posttrain-bench-sft-")

    def trl_run() -> float:
        targs = TRLConfig(learning_rate=lr, max_length=max_len, packing=False, padding_free=False,
                          completion_only_loss=True, **_trl_common(args, tmp, B, bf16))
        return _trl_timed_train(lambda: SFTTrainer(model=copy.deepcopy(base), args=targs,
                                                   train_dataset=Dataset.from_list(data), processing_class=tok),
                                printer, S, tokens, args)

    ctx.runners["trl"] = trl_run
    ctx.cleanup = lambda: shutil.rmtree(tmp, ignore_errors=True)
    return ctx


def bench_sft(args) -> dict:
    ctx = _sft_setup(args)
    repeats = 3 if args.quick else 5
    print(f"tiny: {count_parameters(ctx.base) / 1e6:.2f}M parameters; {ctx.S} steps x {ctx.B} rows, "
          f"{ctx.tokens / (ctx.S * ctx.B):.0f} tokens per row ({ctx.loss_tokens / (ctx.S * ctx.B):.0f} in the loss), "
          f"lr {ctx.lr}, max length {ctx.max_len}")
    if ctx.trl_error is not None:
        _trl_missing(ctx.trl_error)
        t = statistics.median(_alternate(ctx.runners, repeats, args.device)["posttrain"])
        print(f"ours: {ctx.tokens / t:.0f} tokens/s")
        return dict(ours_tok_s=ctx.tokens / t)
    times = _alternate(ctx.runners, repeats, args.device)
    mo, mt = statistics.median(times["posttrain"]), statistics.median(times["trl"])
    print(f"{'implementation':<44} {'tokens/s':>9} {'loss tok/s':>10} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL SFTTrainer':<44} {ctx.tokens / mt:>9.0f} {ctx.loss_tokens / mt:>10.0f} {mt / ctx.S:>7.3f} "
          f"{mt / mo:>6.2f}x")
    print(f"{'posttrain SFT step':<44} {ctx.tokens / mo:>9.0f} {ctx.loss_tokens / mo:>10.0f} {mo / ctx.S:>7.3f} "
          f"{'1.00x':>7}")
    print("ratio = TRL time / posttrain time for the same rows, batches and order.")
    mem = peak_memory("sft", ["posttrain", "trl"], args)
    print_memory(mem, {"posttrain": "posttrain SFT step", "trl": "TRL SFTTrainer"})
    ctx.cleanup()
    return dict(batch=ctx.B, steps=ctx.S, tokens=ctx.tokens, loss_tokens=ctx.loss_tokens,
                ours_tok_s=ctx.tokens / mo, trl_tok_s=ctx.tokens / mt, ratio=mt / mo,
                ours_times=times["posttrain"], trl_times=times["trl"], memory=mem)


def _length_rows(n: int, lo: int, hi: int, vocab: int, seed: int) -> list[list[int]]:
    """n random token lists, lengths log-uniform in [lo, hi] (a long tail of long rows, as in chat data)."""
    rng = random.Random(seed)
    return [[rng.randrange(4, vocab) for _ in range(int(round(lo * (hi / lo) ** rng.random())))] for _ in range(n)]


def bench_microbatch(args) -> dict:
    """Micro-batches of rows of like length against consecutive ones, ours against ours (see the docstring)."""
    from posttrain import loop, sharding
    from posttrain.data import collate_completions, to_device, token_groups
    from posttrain.logprobs import nll_sum, sequence_logprobs

    tok = _summarize_tokenizer()
    base = build_model("small", tok, seed=0).to(args.device)
    V, B, S, budget = len(tok), 16, 2 if args.quick else 4, args.micro_tokens
    repeats = 2 if args.quick else 3
    # SFT: prompt + completion rows, 32-512 tokens (a quarter of them the completion)
    sft_rows = []
    for ids in _length_rows(B * S, 32, 512, V, seed=1):
        k = max(1, len(ids) // 4)
        sft_rows.append((ids[:-k], ids[-k:]))
    # policy update: 2 prompts x 8 completions a step, prompts 40-80 tokens left-padded, completions 8-256
    rng = random.Random(2)
    upd_rows = []
    for _ in range(S):
        for _ in range(2):
            prompt = [rng.randrange(4, V) for _ in range(rng.randrange(40, 81))]
            upd_rows += [(prompt, c) for c in _length_rows(8, 8, 256, V, seed=rng.randrange(10**6))]

    def upd_batch(rows):
        P = max(len(p) for p, _ in rows)
        C = max(len(c) for _, c in rows)
        ids = torch.zeros(len(rows), P + C, dtype=torch.long)
        am, cm = torch.zeros_like(ids), torch.zeros_like(ids)
        for i, (p, c) in enumerate(rows):
            ids[i, P - len(p):P + len(c)] = torch.tensor(p + c)
            am[i, P - len(p):P + len(c)] = 1
            cm[i, P:P + len(c)] = 1
        adv = torch.randn(len(rows), generator=torch.Generator().manual_seed(len(rows)))
        return {"input_ids": ids, "attention_mask": am, "completion_mask": cm, "loss_mask": cm,
                "advantages": adv[:, None].expand(-1, P + C).contiguous()}

    upd_batches = [upd_batch(upd_rows[s * B:(s + 1) * B]) for s in range(S)]

    def padded(mbs):
        return sum(int(mb["input_ids"].numel()) for mb in mbs)

    def sft_mbs(step, by_length):  # as `posttrain sft` groups its rows
        rows = sft_rows[step * B:(step + 1) * B]
        groups = token_groups([(0, len(p) + len(c)) for p, c in rows], 0, budget, by_length=by_length)
        return [collate_completions([rows[i] for i in g], tok.pad_token_id) for g in groups]

    def upd_mbs(step, by_length):
        rows = upd_batches[step]
        return [mb for mb, _, _ in sharding.micro_batches(rows, torch.arange(B), 0, "token_mean", max_tokens=budget,
                                                           by_length=by_length)]

    def runner(make, loss, by_length):
        def run() -> float:
            model = copy.deepcopy(base)
            accelerator = loop.setup(0)
            t0 = time.perf_counter()
            optimizer = loop.build_optimizer(model, 1e-5)
            model, optimizer = accelerator.prepare(model, optimizer)
            scheduler = loop.build_scheduler(optimizer, 0, S, "constant")
            for step in range(S):
                mbs = make(step, by_length)
                n = float(sum(mb["completion_mask"].sum() for mb in mbs))
                mbs = [to_device(mb, args.device) for mb in mbs]  # where the model is
                loop.optimizer_step(accelerator, model, optimizer, scheduler, mbs,
                                    lambda mb: (loss(model, mb) / n, {}), 1.0, step + 1)
            _sync(args.device)
            return time.perf_counter() - t0
        return run

    def sft_loss(model, mb):
        return nll_sum(model, mb)[0]

    def upd_loss(model, mb):
        lp, _ = sequence_logprobs(model, mb["input_ids"], mb["attention_mask"], mb["completion_mask"])
        return -(lp * mb["advantages"] * mb["completion_mask"]).sum()

    print(f"small preset: {count_parameters(base) / 1e6:.2f}M parameters; {S} steps x {B} rows, budget {budget} "
          f"padded tokens per micro-batch; lengths drawn log-uniform (SFT rows 32-512 tokens; update rows: "
          f"prompts 40-80 left-padded, completions 8-256)")
    print(f"{'workload':<34} {'grouping':<12} {'real tok':>8} {'padded':>8} {'micro':>6} {'s/step':>7} {'ratio':>7}")
    out = {}
    for name, make, loss, real in (
            ("SFT step", sft_mbs, sft_loss, sum(len(p) + len(c) for p, c in sft_rows)),
            ("policy update (log-probs + AdamW)", upd_mbs, upd_loss, sum(len(p) + len(c) for p, c in upd_rows))):
        runners = {"consecutive": runner(make, loss, False), "by length": runner(make, loss, True)}
        times = _alternate(runners, repeats, args.device)
        row = {}
        for grouping, by_length in (("consecutive", False), ("by length", True)):
            mbs = [make(s, by_length) for s in range(S)]
            row[grouping] = dict(padded=sum(padded(m) for m in mbs), micro=sum(len(m) for m in mbs) / S,
                                 s_step=statistics.median(times[grouping]) / S, times=times[grouping])
        for grouping in ("consecutive", "by length"):
            r = row[grouping]
            print(f"{name:<34} {grouping:<12} {real:>8} {r['padded']:>8} {r['micro']:>6.1f} {r['s_step']:>7.3f} "
                  f"{row['consecutive']['s_step'] / r['s_step']:>6.2f}x")
        out[name] = dict(real_tokens=real, **row)
    print("ratio = consecutive time / this time, same rows, model, budget and optimizer; medians of alternating runs.")
    return dict(budget=budget, steps=S, batch=B, workloads=out)


# ------------------------------------------------------------------ section: rm


def _rm_setup(args, real: bool = False, bf16: bool = False) -> SimpleNamespace:
    """Our reward-model step and TRL's RewardTrainer over the same S*B pairs (see the module docstring).
    real=True: the real model (--real) under a seeded one-output head, word-math pairs (chosen = the worked answer,
    rejected = another problem's, prompts through the chat template) as DPO's real rows, batch 8 (~1.1k tokens).
    bf16: both under bf16 autocast over fp32 weights (ours run.mixed_precision=bf16, TRL bf16=True)."""
    from posttrain import loop
    from posttrain.losses import bradley_terry_loss
    from posttrain.models import save_model
    from posttrain.preferences import check_pairs
    from posttrain.scoring import rm_appends_eos
    from posttrain.models import load_reward_init
    from posttrain.scoring import pair_rewards

    tmp = tempfile.mkdtemp(prefix="posttrain-bench-rm-")
    if real:
        from posttrain.tasks import get_task

        tok, _ = _real_base(args)
        B, S, lr, max_len = 8, 2 if args.quick else 3, 1e-5, 512
        ex = get_task("word-math").make_examples(S * B + 1, 0, "train")
        rows = [{"prompt": ex[i]["prompt"], "chosen": ex[i]["completion"], "rejected": ex[i + 1]["completion"],
                 "_row": i + 1} for i in range(S * B)]
        lm_dir = args.real
    else:
        B, S, lr, max_len = 16, 6 if args.quick else 16, 1e-4, 256
        tok = _summarize_tokenizer()
        rows = _summarize_pairs(S * B)
        lm_dir = Path(tmp) / "lm"
        save_model(build_model("tiny", tok, seed=0), tok, lm_dir)
    pad = tok.pad_token_id
    _, pairs, _ = check_pairs(rows, "bench pairs", "error", tok, max_len, append_eos=rm_appends_eos(tok))
    tokens = sum(2 * len(p.prompt) + len(p.chosen) + len(p.rejected) for p in pairs)
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):  # "new head" report
        base = load_reward_init(lm_dir, pad, 0, args.device)

    def ours() -> float:
        model = copy.deepcopy(base)
        accelerator = loop.setup(0, mixed_precision="bf16" if bf16 else None)
        t0 = time.perf_counter()
        optimizer = loop.build_optimizer(model, lr)
        model, optimizer = accelerator.prepare(model, optimizer)  # as the trainer does (its autocast under bf16)
        scheduler = loop.build_scheduler(optimizer, 0, S, "constant")
        for step in range(S):
            def loss_fn(chunk):
                r = pair_rewards(model, chunk, pad)  # (2b,) chosen then rejected, one forward
                return bradley_terry_loss(r[: len(chunk)], r[len(chunk):])

            loop.optimizer_step(accelerator, model, optimizer, scheduler, [pairs[step * B:(step + 1) * B]],
                                loss_fn, 1.0, step + 1)
        _sync(args.device)
        return time.perf_counter() - t0

    ctx = SimpleNamespace(B=B, S=S, lr=lr, tokens=tokens, loss_tokens=None, base=base, runners={"posttrain": ours},
                          trl_error=None, cleanup=lambda: shutil.rmtree(tmp, ignore_errors=True))
    try:
        from datasets import Dataset
        from trl import RewardConfig as TRLConfig, RewardTrainer
    except ImportError as e:
        ctx.trl_error = e
        return ctx
    printer = _trl_quiet()
    data = [{"chosen_ids": p.prompt + p.chosen, "rejected_ids": p.prompt + p.rejected} for p in pairs]

    def trl_run() -> float:
        targs = TRLConfig(learning_rate=lr, max_length=max_len, disable_dropout=True,
                          center_rewards_coefficient=None, **_trl_common(args, str(Path(tmp) / "trl"), B, bf16))
        return _trl_timed_train(lambda: RewardTrainer(model=copy.deepcopy(base), args=targs,
                                                      train_dataset=Dataset.from_list(data), processing_class=tok),
                                printer, S, tokens, args)

    ctx.runners["trl"] = trl_run
    return ctx


def bench_rm(args) -> dict:
    ctx = _rm_setup(args)
    repeats = 3 if args.quick else 5
    n = ctx.S * ctx.B
    print(f"tiny reward model: {count_parameters(ctx.base) / 1e6:.2f}M parameters; {ctx.S} steps x {ctx.B} pairs, "
          f"{ctx.tokens / n:.0f} tokens per pair (prompt + chosen, prompt + rejected), lr {ctx.lr}")
    if ctx.trl_error is not None:
        _trl_missing(ctx.trl_error)
        t = statistics.median(_alternate(ctx.runners, repeats, args.device)["posttrain"])
        print(f"ours: {n / t:.1f} pairs/s")
        ctx.cleanup()
        return dict(ours_pairs_s=n / t)
    times = _alternate(ctx.runners, repeats, args.device)
    mo, mt = statistics.median(times["posttrain"]), statistics.median(times["trl"])
    print(f"{'implementation':<44} {'pairs/s':>8} {'tokens/s':>9} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL RewardTrainer':<44} {n / mt:>8.1f} {ctx.tokens / mt:>9.0f} {mt / ctx.S:>7.3f} {mt / mo:>6.2f}x")
    print(f"{'posttrain reward-model step':<44} {n / mo:>8.1f} {ctx.tokens / mo:>9.0f} {mo / ctx.S:>7.3f} {'1.00x':>7}")
    print("ratio = TRL time / posttrain time for the same pairs, batches and order.")
    mem = peak_memory("rm", ["posttrain", "trl"], args)
    print_memory(mem, {"posttrain": "posttrain reward-model step", "trl": "TRL RewardTrainer"})
    ctx.cleanup()
    return dict(batch=ctx.B, steps=ctx.S, tokens=ctx.tokens, ours_pairs_s=n / mo, trl_pairs_s=n / mt,
                ratio=mt / mo, ours_times=times["posttrain"], trl_times=times["trl"], memory=mem)


# ------------------------------------------------------------------ section: dpo


def _dpo_setup(args, real: bool = False, bf16: bool = False) -> SimpleNamespace:
    """Our DPO training loop against TRL's DPOTrainer on the same tiny model, pairs, batch and lr.

    Both train one pass over the same S*B pairs (S steps of B pairs), so they process exactly the same
    tokens; tokens/s = (prompt+chosen + prompt+rejected tokens of those pairs) / wall time. Ours is timed
    from the reference precompute (the SFT model's log-probs of every pair, done once) to the last
    optimizer step; TRL's from its first step (`_first_step_clock`) to the return of `train()` (its reference
    model runs every step,
    its default); with precompute_ref_log_probs=True (second row) TRL computes them in its constructor, so
    a second, identical precompute pass is timed alone and added to its train() time. TRL is configured for
    this CPU: fp32 (bf16=False), gradient_checkpointing=False, no logging / saving / eval, our batch order.
    real=True: word-math pairs (chosen = the worked answer, rejected = another problem's) on the real model (--real),
    prompts through its chat template (TRL is given them rendered, so both tokenize the same text), batch 4.
    bf16: both under bf16 autocast over fp32 weights (ours run.mixed_precision=bf16, TRL bf16=True).
    """
    from posttrain import loop
    from posttrain.losses import dpo_loss
    from posttrain.data import collate_pairs
    from posttrain.preferences import check_pairs, pair_logps, reference_logps

    if real:
        from posttrain import chat
        from posttrain.tasks import get_task

        tok, base = _real_base(args)
        B, S, max_len, lr = 4, 2 if args.quick else 3, 512, 1e-6
        ex = get_task("word-math").make_examples(S * B + 1, 0, "train")
        rows = [{"prompt": ex[i]["prompt"], "chosen": ex[i]["completion"], "rejected": ex[i + 1]["completion"],
                 "_row": i + 1} for i in range(S * B)]
        trl_rows = [dict(r, prompt=chat.render_prompt(tok, r["prompt"])) for r in rows]
    else:
        B, S, max_len, lr = args.dpo_batch, 6 if args.quick else 16, 256, 1e-4
        tok = _summarize_tokenizer()
        rows = trl_rows = _summarize_pairs(S * B)
        base = build_model("tiny", tok, seed=0).to(args.device)
    _, pairs, _ = check_pairs(rows, "bench pairs", "error", tok, max_len)
    tokens = sum(2 * len(p.prompt) + len(p.chosen) + len(p.rejected) for p in pairs)
    beta = 0.1  # the sigmoid DPO loss (posttrain dpo's default loss_type)
    pad = tok.pad_token_id

    def ours() -> float:
        model = copy.deepcopy(base)
        accelerator = loop.setup(0, mixed_precision="bf16" if bf16 else None)
        t0 = time.perf_counter()
        with accelerator.autocast():  # once, in the run's precision, as the trainer does
            ref = reference_logps(model, pairs, pad, B)
        optimizer = loop.build_optimizer(model, lr)
        model, optimizer = accelerator.prepare(model, optimizer)  # as the trainer does (its autocast under bf16)
        scheduler = loop.build_scheduler(optimizer, 0, S, "constant")
        for step in range(S):
            idx = list(range(step * B, (step + 1) * B))
            batch = collate_pairs([pairs[i] for i in idx], pad, share_prompt=True)
            r = {k: v[idx] for k, v in ref.items()}

            def loss_fn(mb):
                s, _ = pair_logps(model, mb)  # (2B,): chosen, then rejected
                return dpo_loss(s[:B], s[B:], r["chosen"], r["rejected"], beta=beta, loss_type="sigmoid")

            loop.optimizer_step(accelerator, model, optimizer, scheduler, [batch], loss_fn, 1.0, step + 1)
        _sync(args.device)
        return time.perf_counter() - t0

    ctx = SimpleNamespace(B=B, S=S, tokens=tokens, n_pairs=len(pairs), base=base, runners={"posttrain": ours},
                          trl_error=None)
    try:
        import trl  # noqa: F401
        from datasets import Dataset
        from trl import DPOConfig as TRLConfig, DPOTrainer
    except ImportError as e:
        ctx.trl_error = e
        return ctx
    printer = _trl_quiet()
    data = [{k: r[k] for k in ("prompt", "chosen", "rejected")} for r in trl_rows]
    tmp = tempfile.mkdtemp(prefix="posttrain-bench-trl-")

    def trl_run(precompute: bool = False) -> float:
        targs = TRLConfig(precompute_ref_log_probs=precompute, precompute_ref_batch_size=B, learning_rate=lr,
                          beta=beta, max_length=max_len, **_trl_common(args, tmp, B, bf16))
        ref = None if precompute else copy.deepcopy(base).eval()
        train_data = Dataset.from_list(data)
        train_data._fingerprint = f"posttrain-bench-{time.time_ns()}"  # no reuse of TRL's cached reference log-probs
        model = copy.deepcopy(base)
        with contextlib.redirect_stderr(io.StringIO()):  # TRL's own progress bars
            trainer = DPOTrainer(model=model, ref_model=ref, args=targs, train_dataset=train_data,
                                 processing_class=tok)
            trainer.remove_callback(printer)
            clock = _first_step_clock()
            trainer.add_callback(clock)
            t_pre = 0.0
            if precompute:  # TRL ran it in the constructor (with dataset bookkeeping): time one more pass alone
                ds = trainer.train_dataset.remove_columns(["ref_chosen_logps", "ref_rejected_logps"])
                ds._fingerprint = f"posttrain-bench-{time.time_ns()}"
                t0 = time.perf_counter()
                trainer._precompute_ref_logps(ds, "train", B)
                t_pre = time.perf_counter() - t0
            out = trainer.train()
        _sync(args.device)
        dt = time.perf_counter() - clock.t0 + t_pre
        assert out.global_step == S, f"TRL ran {out.global_step} steps, expected {S}"
        assert not trainer.args.gradient_checkpointing, "TRL ran with activation checkpointing"
        return dt

    ctx.runners.update(trl=trl_run, trl_precompute=lambda: trl_run(True))
    ctx.cleanup = lambda: shutil.rmtree(tmp, ignore_errors=True)
    return ctx


def bench_dpo(args) -> dict:
    ctx = _dpo_setup(args)
    S, B, tokens = ctx.S, ctx.B, ctx.tokens
    repeats = 3 if args.quick else 5
    print(f"tiny: {count_parameters(ctx.base) / 1e6:.2f}M parameters; {S} steps x {B} pairs, "
          f"{tokens / ctx.n_pairs:.0f} tokens per pair (prompt twice + chosen + rejected), lr 1e-4, beta 0.1")
    if ctx.trl_error is not None:
        _trl_missing(ctx.trl_error)
        t = statistics.median(_alternate(ctx.runners, repeats, args.device)["posttrain"])
        print(f"ours: {tokens / t:.0f} tokens/s")
        return dict(ours_tok_s=tokens / t)
    times = _alternate({k: ctx.runners[k] for k in ("trl", "posttrain", "trl_precompute")}, repeats, args.device)
    t_ours, t_trl, t_trl_pre = times["posttrain"], times["trl"], times["trl_precompute"]
    mo, mt, mp = statistics.median(t_ours), statistics.median(t_trl), statistics.median(t_trl_pre)
    print(f"{'implementation':<44} {'tokens/s':>9} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL DPOTrainer, live reference (its default)':<44} {tokens / mt:>9.0f} {mt / S:>7.3f} "
          f"{mt / mo:>6.2f}x")
    print(f"{'TRL DPOTrainer, precompute_ref_log_probs':<44} {tokens / mp:>9.0f} {mp / S:>7.3f} {mp / mo:>6.2f}x")
    print(f"{'posttrain DPO loop (reference precomputed)':<44} {tokens / mo:>9.0f} {mo / S:>7.3f} {'1.00x':>7}")
    print("ratio = TRL time / posttrain time for the same pairs (both include their reference log-probs).")
    impls = ["posttrain", "trl"] + ([] if args.quick else ["trl_precompute"])
    mem = peak_memory("dpo", impls, args)
    print_memory(mem, {"posttrain": "posttrain DPO loop", "trl": "TRL DPOTrainer, live reference",
                       "trl_precompute": "TRL DPOTrainer, precompute_ref_log_probs"})
    ctx.cleanup()
    return dict(batch=B, steps=S, tokens=tokens, ours_tok_s=tokens / mo, trl_tok_s=tokens / mt,
                trl_precompute_tok_s=tokens / mp, ratio=mt / mo, ratio_vs_trl_precompute=mp / mo,
                ours_times=t_ours, trl_times=t_trl, trl_precompute_times=t_trl_pre, memory=mem)


# ------------------------------------------------------------------ section: ppo


def _trl_ppo_status() -> str | None:
    """Where an importable TRL PPOTrainer lives, or None (TRL missing, or a version without one)."""
    import importlib
    import warnings

    for mod in ("trl", "trl.experimental.ppo"):
        try:
            with warnings.catch_warnings():  # importing trl.experimental warns that it is experimental
                warnings.simplefilter("ignore")
                if hasattr(importlib.import_module(mod), "PPOTrainer"):
                    return f"{mod}.PPOTrainer"
        except ImportError:
            pass
    return None


def _ppo_setup(args) -> SimpleNamespace:
    """`posttrain ppo` through the CLI on a throwaway recipe, its phases read from the metrics it logs.

    Random-init tiny policy (= SFT model) and a reward model made of the same transformer under a seeded
    one-output head (value_init=reward copies it), tiny-summarize prompts, rollout batch 16 (quick) / 32,
    minibatch 8, 2 PPO epochs, <= max_new_tokens new tokens (a random model rarely samples eos), reward
    normalisation per batch (no initial sampling pass), no evaluation. The trainer logs time/rollout_s,
    time/score_s and time/iteration_s per iteration; the update is the rest of the iteration.
    """
    from posttrain.cli import main as posttrain_main
    from posttrain.models import load_reward_init, save_model

    iters = 4 if args.quick else 8
    rollout, minibatch, epochs = (16 if args.quick else 32), 8, 2
    root = Path(tempfile.mkdtemp(prefix="posttrain-bench-ppo-"))
    tok = _summarize_tokenizer()
    base = build_model("tiny", tok, seed=0)
    save_model(base, tok, root / "model")
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):  # "new head" report
        save_model(load_reward_init(root / "model", tok.pad_token_id, 0, "cpu"), tok, root / "rm")
    sft = root / "runs" / "bench-ppo" / "sft" / "final"
    sft.parent.mkdir(parents=True)
    shutil.copytree(root / "model", sft)
    recipe = root / "bench-ppo.yaml"
    recipe.write_text(f"""# PPO iteration benchmark (scripts/bench.py); posttrain ppo --recipe this file
task: {{name: tiny-summarize, n_train: 64, n_eval: 8}}
model: {{path: {root / 'model'}, max_length: 256}}
ppo:
  reward_model: {root / 'rm'}
  rollout_batch_size: {rollout}
  minibatch_size: {minibatch}
  ppo_epochs: {epochs}
  max_new_tokens: {args.max_new_tokens}
  reward_norm: batch
  eval_every: 0
  eval_rows: 0
  final_eval_rows: 0
  save_every: 0
""")

    def ours() -> list[dict[str, float]]:
        with contextlib.redirect_stdout(io.StringIO()):
            rc = posttrain_main(["ppo", "--recipe", str(recipe), f"run.output_dir={root / 'runs'}",
                                 f"run.threads={args.threads}", "run.quiet=true", f"max_steps={iters}"])
        assert rc == 0, "posttrain ppo failed"
        rows = [json.loads(l) for l in (root / "runs" / "bench-ppo" / "ppo" / "metrics.jsonl").read_text().splitlines()]
        rows = [r for r in rows if "time/iteration_s" in r]
        assert len(rows) == iters, (len(rows), iters)
        return [{"iteration": r["time/iteration_s"], "rollout": r["time/rollout_s"], "scoring": r["time/score_s"],
                 "update": r["time/iteration_s"] - r["time/rollout_s"] - r["time/score_s"],
                 "length": r["rollout/length"]} for r in rows][1:]  # the first iteration is warm-up

    return SimpleNamespace(iters=iters, rollout=rollout, minibatch=minibatch, epochs=epochs, base=base,
                           runners={"posttrain": ours}, cleanup=lambda: shutil.rmtree(root, ignore_errors=True))


def bench_ppo(args) -> dict:
    ctx = _ppo_setup(args)
    rounds = 1 if args.quick else 2
    n_mb = ctx.rollout // ctx.minibatch
    print(f"tiny policy, value and reward models ({count_parameters(ctx.base) / 1e6:.2f}M parameters each); "
          f"{ctx.rollout} prompts x 1 completion x <= {args.max_new_tokens} tokens per iteration, {ctx.epochs} epochs "
          f"x {n_mb} minibatches of {ctx.minibatch}; {ctx.iters} iterations per run ({rounds} run(s), first excluded)")
    its: list[dict[str, float]] = []
    for _ in range(rounds):
        its += ctx.runners["posttrain"]()
    med = {k: statistics.median(i[k] for i in its) for k in ("iteration", "rollout", "scoring", "update", "length")}
    print(f"{'phase (medians)':<58} {'s/iter':>7} {'share':>6}")
    for k, what in (("rollout", "rollout (engine sampling)"), ("scoring", "scoring (reward model on the text)"),
                    ("update", "update (old/ref/value forwards, GAE, PPO minibatches)")):
        print(f"{what:<58} {med[k]:>7.3f} {100 * med[k] / med['iteration']:>5.0f}%")
    print(f"{'posttrain ppo iteration':<58} {med['iteration']:>7.3f}")
    print(f"{ctx.rollout * med['length'] / med['iteration']:.0f} completion tokens/s over the whole iteration "
          f"({med['length']:.1f} tokens per completion)")
    where = _trl_ppo_status()
    if where is None:
        history = ("TRL moved PPOTrainer to trl.experimental.ppo in 1.10 (huggingface/trl#4482) and later deleted "
                   "it (huggingface/trl#7020)")
        try:
            import trl
            why = f"TRL {trl.__version__} has no PPO trainer: {history}"
        except ImportError:
            why = f"TRL is not installed, and its current releases have no PPO trainer anyway: {history}"
    else:
        why = (f"{where} exists in this TRL, but this section has no driver for it (its API takes pre-tokenized "
               "prompts and value-head models); nothing was measured against it")
    print(f"no TRL baseline, no ratio: {why}.")
    mem = peak_memory("ppo", ["posttrain"], args)
    print_memory(mem, {"posttrain": "posttrain ppo (policy, reference, value, reward)"})
    ctx.cleanup()
    return dict(rollout_batch=ctx.rollout, minibatch=ctx.minibatch, ppo_epochs=ctx.epochs, s_per_iteration=med,
                iterations=its, trl_baseline=None, no_baseline_reason=why, memory=mem)


# ------------------------------------------------------------------ section: grpo


def _grpo_setup(args, real: bool = False) -> SimpleNamespace:
    """A GRPO step of `posttrain grpo` (the trainer itself, run through the CLI) against one of TRL's GRPOTrainer.

    Same random-init tiny model and tokenizer (vocabulary 1024), the same 64 prompts of 20 words, 2 prompts x
    8 completions per step, at most 64 new tokens (a random model rarely samples eos, so rows run ~60 tokens
    on both sides), temperature 1, the same reward (the length verifier, 150 characters budget: rewards vary
    within groups), beta 0 (no reference model), one pass per batch, group-std advantages, token-mean loss
    (TRL's "dapo"), lr 1e-4 constant, gradient clipping 1.0. TRL is configured for this CPU: fp32 (bf16=False),
    gradient_checkpointing=False, no logging / saving. Time per step: ours is metrics.jsonl's time/step
    (sampling + scoring + update); TRL's is timed between its on_step_begin and on_step_end callbacks (its
    generation happens inside the step). The first 2 steps of every run are warm-up and excluded; runs
    alternate; medians over all remaining steps.
    real=True: the real model (--real) as it is (model.start_from=base), 2 prompts x 4 completions, word-math
    held-out prompts through its chat template (TRL gets them as one-message conversations, so it applies the same
    template), max length 512. Each runner takes bf16=True for bf16 on both sides: TRL bf16=True (autocast over
    fp32 weights, its generation included, as accelerate wraps the model's forward); ours
    run.mixed_precision=bf16 with rollout.dtype=bfloat16 (the engine's bf16 sampling weights).
    """
    from posttrain.cli import STAGES, main as posttrain_main

    STAGES["grpo"].load()  # the trainer imported before any memory baseline, as the CLI would
    from posttrain.models import save_model
    from posttrain.verifiers.format import LengthVerifier

    root = Path(tempfile.mkdtemp(prefix="posttrain-bench-grpo-"))
    if real:
        from posttrain.tasks import get_task

        # lr 1e-7: the weights barely move, so neither side's completions shrink under the length reward within
        # the run (a step's cost follows the generated length; at 1e-4 ours fell from ~60 to ~30 tokens in 3 steps)
        steps, group, max_len, lr = 5 if args.quick else 7, 4, 512, 1e-7
        tok, base = _real_base(args)
        model_dir, start_from = Path(args.real).resolve(), "base"
        prompts = [r["prompt"] for r in get_task("word-math").make_examples(64, 0, "eval")]
    else:
        steps, group, max_len, lr = 8 if args.quick else 14, 8, 256, 1e-4
        corpus = _corpus(300)
        tok = train_tokenizer(corpus, vocab_size=1024)
        base = build_model("tiny", tok, seed=0)
        model_dir, start_from = root / "model", "sft"
        save_model(base, tok, model_dir)
        prompts = [" ".join(c.split()[:20]) for c in corpus[:64]]
    (root / "problems.jsonl").write_text("".join(json.dumps({"prompt": p, "answer": "-", "verifier": "length"}) + "\n"
                                                for p in prompts))
    recipe = root / "bench-grpo.yaml"
    recipe.write_text(f"""# GRPO step benchmark (scripts/bench.py); posttrain grpo --recipe this file, ~1 min
task: {{name: tiny-countdown, n_train: 16, n_eval: 8}}
model: {{path: {model_dir}, max_length: {max_len}, start_from: {start_from}}}
grpo:
  verifier: length
  verifier_options: {{max_chars: 150}}
  verifier_workers: 0
  train_file: {root / 'problems.jsonl'}
  prompts_per_step: 2
  group_size: {group}
  max_new_tokens: {args.max_new_tokens}
  zero_variance: keep
  lr: {lr:.1e}
  eval_every: 0
  eval_rows: 0
  final_eval_rows: 0
  save_every: 0
""")
    if not real:
        sft = root / "runs" / "bench-grpo" / "sft" / "final"
        sft.parent.mkdir(parents=True)
        shutil.copytree(model_dir, sft)

    def ours(*overrides: str, bf16: bool = False) -> tuple[list[float], dict[str, float]]:
        precision = ["run.mixed_precision=bf16", "rollout.dtype=bfloat16"] if bf16 else []
        with contextlib.redirect_stdout(io.StringIO()):
            rc = posttrain_main(["grpo", "--recipe", str(recipe), f"run.output_dir={root / 'runs'}",
                                 f"run.threads={args.threads}", "run.quiet=true", f"max_steps={steps}", *precision,
                                 *overrides])
        assert rc == 0, "posttrain grpo failed"
        return _cli_step_times(root / "runs" / "bench-grpo" / "grpo" / "metrics.jsonl", ("sample", "score", "train"))

    ctx = SimpleNamespace(steps=steps, group=group, base=base, runners={"posttrain": ours}, trl_error=None,
                          cleanup=lambda: shutil.rmtree(root, ignore_errors=True))
    try:
        from datasets import Dataset
        from trl import GRPOConfig as TRLConfig, GRPOTrainer
    except ImportError as e:
        ctx.trl_error = e
        return ctx
    printer = _trl_quiet()
    length = LengthVerifier(max_chars=150)

    def length_reward(completions, **kwargs):
        # a conversational prompt gets its completions as messages: score the text of the reply
        return [length.check(c if isinstance(c, str) else "".join(m["content"] for m in c), None).score
                for c in completions]

    trl_prompts = [[{"role": "user", "content": p}] for p in prompts] if real else prompts

    def trl_run(bf16: bool = False, **method) -> list[float]:
        targs = TRLConfig(output_dir=str(root / "trl"), per_device_train_batch_size=2 * group, num_generations=group,
                          max_completion_length=args.max_new_tokens, temperature=1.0, beta=0.0, num_iterations=1,
                          learning_rate=lr, lr_scheduler_type="constant", max_grad_norm=1.0, max_steps=steps,
                          bf16=bf16, fp16=False, **_no_checkpointing(), use_cpu=args.device == "cpu",
                          logging_strategy="no", save_strategy="no", report_to=[], disable_tqdm=True,
                          dataloader_num_workers=0, seed=0, **method)
        timer = _step_timer(args.device, "completions/mean_length")  # the step's mean completion length too
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            trainer = GRPOTrainer(model=copy.deepcopy(base), reward_funcs=[length_reward], args=targs,
                                  train_dataset=Dataset.from_list([{"prompt": p} for p in trl_prompts]),
                                  processing_class=tok, callbacks=[timer])
            trainer.remove_callback(printer)
            timer.trainer = trainer
            out = trainer.train()
        assert out.global_step == steps, f"TRL ran {out.global_step} steps, expected {steps}"
        assert not trainer.args.gradient_checkpointing, "TRL ran with activation checkpointing"
        ctx.trl_completion_tokens = statistics.mean(timer.values[2:])
        return timer.times[2:]

    ctx.runners["trl"] = trl_run
    return ctx


def bench_grpo(args) -> dict:
    ctx = _grpo_setup(args)
    steps = ctx.steps
    rounds = 1 if args.quick else 2
    print(f"tiny: {count_parameters(ctx.base) / 1e6:.2f}M parameters; 2 prompts x 8 completions x <= "
          f"{args.max_new_tokens} tokens per step, {steps} steps per run ({rounds} run(s) each, first 2 steps excluded)")
    if ctx.trl_error is not None:
        _trl_missing(ctx.trl_error)
        t, phases = ctx.runners["posttrain"]()
        print(f"ours: {statistics.median(t):.3f} s/step ({phases})")
        ctx.cleanup()
        return dict(ours_s_per_step=statistics.median(t), ours_phases=phases)
    t_ours, t_trl, phases = [], [], {}
    for _ in range(rounds):  # alternate, so drifting load hits both
        t, phases = ctx.runners["posttrain"]()
        t_ours += t
        t_trl += ctx.runners["trl"]()
    mo, mt = statistics.median(t_ours), statistics.median(t_trl)
    print(f"{'implementation':<58} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL GRPOTrainer (fp32, no gradient checkpointing)':<58} {mt:>7.3f} {mt / mo:>6.2f}x")
    print(f"{'posttrain grpo':<58} {mo:>7.3f} {'1.00x':>7}")
    print(f"posttrain phases (medians): sample {phases['sample']:.3f} s, score {phases['score']:.3f} s, "
          f"update {phases['train']:.3f} s; {phases['completion_tokens']:.1f} completion tokens per row")
    print("ratio = TRL time per step / posttrain time per step, same model, prompts, group size and budget.")
    # GSPO (Zheng et al. 2025) as both sides name it: one clipped ratio per sequence, the paper's clip ranges,
    # a mean over sequences (TRL: importance_sampling_level="sequence" with loss_type="grpo")
    g_ours, g_trl = [], []
    for _ in range(rounds):
        g_ours += ctx.runners["posttrain"]("policy_loss=gspo", "aggregation=seq_mean_token_mean", "clip_eps=3e-4",
                                           "clip_eps_high=4e-4")[0]
        g_trl += ctx.runners["trl"](importance_sampling_level="sequence", loss_type="grpo", epsilon=3e-4,
                                    epsilon_high=4e-4)
    go, gt = statistics.median(g_ours), statistics.median(g_trl)
    print(f"{'TRL GRPOTrainer, GSPO (importance_sampling_level=sequence)':<58} {gt:>7.3f} {gt / go:>6.2f}x")
    print(f"{'posttrain grpo policy_loss=gspo':<58} {go:>7.3f} {'1.00x':>7}")
    mem = peak_memory("grpo", ["posttrain", "trl"], args)
    print_memory(mem, {"posttrain": f"posttrain grpo ({steps} steps)", "trl": f"TRL GRPOTrainer ({steps} steps)"})
    ctx.cleanup()
    return dict(steps_per_run=steps, rounds=rounds, ours_s_per_step=mo, trl_s_per_step=mt, ratio=mt / mo,
                ours_phases=phases, ours_times=t_ours, trl_times=t_trl, memory=mem,
                gspo=dict(ours_s_per_step=go, trl_s_per_step=gt, ratio=gt / go))


# ------------------------------------------------------------------ section: distill


def _distill_setup(args, real: bool = False) -> SimpleNamespace:
    """An on-policy distillation step of `posttrain distill` (the trainer, through the CLI) against TRL's
    DistillationTrainer (TRL >= 1.x; GKD's on-policy loss).

    Same random-init tiny student and tokenizer (vocabulary 1024), a teacher of the `small` preset (another seed,
    same tokenizer), the same 64 prompts of 20 words, 16 prompts x 1 completion per step, at most 64 new tokens
    (a random model rarely samples eos, so rows run ~60 tokens on both sides), temperature 1, the per-token reverse
    KL over the full vocabulary (ours: loss=reverse_kl; TRL: beta=1.0), lr 1e-4 constant, clipping 1.0. TRL is
    configured for this CPU: fp32, gradient checkpointing off, no logging / saving. Time per step: ours is
    metrics.jsonl's time/step (sampling + teacher + update); TRL's is timed between its on_step_begin and
    on_step_end callbacks (its generation happens inside the step). The first 2 steps of every run are warm-up
    and excluded; runs alternate; medians over all remaining steps.
    real=True: the real model (--real) as student (model.start_from=base) and as teacher (the one real model at hand:
    self-distillation, the same work per step as a distinct teacher of its size), 8 word-math held-out prompts per
    step through its chat template (TRL gets one-message conversations, so it applies the same template), lr 1e-7,
    max length 512. Each runner takes bf16=True for bf16 on both sides (ours run.mixed_precision=bf16 and
    rollout.dtype=bfloat16; TRL bf16=True).
    """
    from posttrain.cli import STAGES, main as posttrain_main

    STAGES["distill"].load()
    from posttrain.models import save_model

    root = Path(tempfile.mkdtemp(prefix="posttrain-bench-distill-"))
    if real:
        from posttrain.tasks import get_task

        steps, per_step, max_len, lr = 4 if args.quick else 6, 8, 512, 1e-7
        tok, student = _real_base(args)
        teacher = student
        student_dir = teacher_dir = Path(args.real).resolve()
        prompts = [r["prompt"] for r in get_task("word-math").make_examples(64, 0, "eval")]
    else:
        steps, per_step, max_len, lr = 8 if args.quick else 14, 16, 256, 1e-4
        corpus = _corpus(300)
        tok = train_tokenizer(corpus, vocab_size=1024)
        student = build_model("tiny", tok, seed=0)
        teacher = build_model("small", tok, seed=1)
        student_dir, teacher_dir = root / "student", root / "teacher"
        save_model(student, tok, student_dir)
        save_model(teacher, tok, teacher_dir)
        prompts = [" ".join(c.split()[:20]) for c in corpus[:64]]
    (root / "prompts.jsonl").write_text("".join(json.dumps({"prompt": p}) + "\n" for p in prompts))
    recipe = root / "bench-distill.yaml"
    recipe.write_text(f"""# on-policy distillation step benchmark (scripts/bench.py); posttrain distill --recipe this file, ~1 min
task: {{name: tiny-countdown, n_train: 16, n_eval: 8}}
model: {{path: {student_dir}, max_length: {max_len}, start_from: {'base' if real else 'sft'}}}
distill:
  teacher: {teacher_dir}
  verifier: none
  train_file: {root / 'prompts.jsonl'}
  prompts_per_step: {per_step}
  max_new_tokens: {args.max_new_tokens}
  lr: {lr:.1e}
  eval_every: 0
  save_every: 0
""")
    if not real:
        sft = root / "runs" / "bench-distill" / "sft" / "final"
        sft.parent.mkdir(parents=True)
        shutil.copytree(student_dir, sft)

    def ours(bf16: bool = False) -> tuple[list[float], dict[str, float]]:
        precision = ["run.mixed_precision=bf16", "rollout.dtype=bfloat16"] if bf16 else []
        with contextlib.redirect_stdout(io.StringIO()):
            rc = posttrain_main(["distill", "--recipe", str(recipe), f"run.output_dir={root / 'runs'}",
                                 f"run.threads={args.threads}", "run.quiet=true", f"max_steps={steps}", *precision])
        assert rc == 0, "posttrain distill failed"
        return _cli_step_times(root / "runs" / "bench-distill" / "distill" / "metrics.jsonl", ("sample", "train"))

    ctx = SimpleNamespace(steps=steps, per_step=per_step, student=student, teacher=teacher,
                          runners={"posttrain": ours}, trl_error=None,
                          cleanup=lambda: shutil.rmtree(root, ignore_errors=True))
    try:
        from datasets import Dataset
        from trl import DistillationConfig, DistillationTrainer
    except ImportError as e:
        ctx.trl_error = e
        return ctx
    printer = _trl_quiet()
    trl_tok = copy.deepcopy(tok)
    trl_tok.padding_side = "left"  # TRL's generation needs left padding

    trl_prompts = [[{"role": "user", "content": p}] for p in prompts] if real else prompts

    def trl_run(bf16: bool = False) -> list[float]:
        targs = DistillationConfig(output_dir=str(root / "trl"), per_device_train_batch_size=per_step,
                                   max_completion_length=args.max_new_tokens, temperature=1.0, beta=1.0,
                                   learning_rate=lr, lr_scheduler_type="constant", max_grad_norm=1.0,
                                   max_steps=steps, bf16=bf16, fp16=False, **_no_checkpointing(),
                                   use_cpu=args.device == "cpu", logging_strategy="no", save_strategy="no",
                                   report_to=[], disable_tqdm=True, dataloader_num_workers=0, seed=0)
        timer = _step_timer(args.device)
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            trainer = DistillationTrainer(model=copy.deepcopy(student), teacher_model=copy.deepcopy(teacher),
                                          args=targs,
                                          train_dataset=Dataset.from_list([{"prompt": p} for p in trl_prompts]),
                                          processing_class=trl_tok, callbacks=[timer])
            trainer.remove_callback(printer)
            out = trainer.train()
        assert out.global_step == steps, f"TRL ran {out.global_step} steps, expected {steps}"
        assert not trainer.args.gradient_checkpointing, "TRL ran with activation checkpointing"
        return timer.times[2:]

    ctx.runners["trl"] = trl_run
    return ctx


def bench_distill(args) -> dict:
    ctx = _distill_setup(args)
    steps, rounds = ctx.steps, 1 if args.quick else 2
    print(f"student tiny {count_parameters(ctx.student) / 1e6:.2f}M, teacher small {count_parameters(ctx.teacher) / 1e6:.2f}M "
          f"parameters; 16 prompts x 1 completion x <= {args.max_new_tokens} tokens per step, reverse KL over the "
          f"vocabulary, {steps} steps per run ({rounds} run(s) each, first 2 steps excluded)")
    if ctx.trl_error is not None:
        _trl_missing(ctx.trl_error)
        t, phases = ctx.runners["posttrain"]()
        print(f"ours: {statistics.median(t):.3f} s/step ({phases})")
        ctx.cleanup()
        return dict(ours_s_per_step=statistics.median(t), ours_phases=phases)
    t_ours, t_trl, phases = [], [], {}
    for _ in range(rounds):  # alternate, so drifting load hits both
        t, phases = ctx.runners["posttrain"]()
        t_ours += t
        t_trl += ctx.runners["trl"]()
    mo, mt = statistics.median(t_ours), statistics.median(t_trl)
    print(f"{'implementation':<58} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL DistillationTrainer (beta 1: reverse KL; fp32)':<58} {mt:>7.3f} {mt / mo:>6.2f}x")
    print(f"{'posttrain distill (loss=reverse_kl)':<58} {mo:>7.3f} {'1.00x':>7}")
    print(f"posttrain phases (medians): sample {phases['sample']:.3f} s, teacher + update {phases['train']:.3f} s; "
          f"{phases['completion_tokens']:.1f} completion tokens per row")
    print("ratio = TRL time per step / posttrain time per step, same student, teacher, prompts and budget.")
    mem = peak_memory("distill", ["posttrain", "trl"], args)
    print_memory(mem, {"posttrain": f"posttrain distill ({steps} steps)",
                       "trl": f"TRL DistillationTrainer ({steps} steps)"})
    ctx.cleanup()
    return dict(steps_per_run=steps, rounds=rounds, ours_s_per_step=mo, trl_s_per_step=mt, ratio=mt / mo,
                ours_phases=phases, ours_times=t_ours, trl_times=t_trl, memory=mem)


# ------------------------------------------------------------------ section: scaling


def bench_scaling(args) -> dict:
    """Cost against model size and sequence length: the rollout engine and a training step (module docstring)."""
    from posttrain import loop
    from posttrain.logprobs import sequence_logprobs

    peak = matmul_peak(args)
    repeats = 3 if args.quick else 5
    gen_batch, prompt_len, train_batch = 16, 32, 8
    gen_lens = (64, 128) if args.quick else (64, 128, 256)
    train_lens = (64, 128, 256)
    corpus = _corpus(300)
    tok = train_tokenizer(corpus, vocab_size=1024)
    enc = [tok(c)["input_ids"] for c in corpus]
    prompts = [enc[i][:prompt_len] for i in range(gen_batch)]
    assert all(len(p) == prompt_len for p in prompts)
    print(f"generate: batch {gen_batch}, {prompt_len}-token prompts, sampling at temperature 1 (eos ignored); "
          f"train: batch {train_batch} unpadded rows, LM loss on every token, forward + backward + AdamW step; "
          f"medians of {repeats} after a warm-up")
    print(f"{'preset':<6} {'params':>7} {'kind':<8} {'length':>6} {'s/call':>8} {'tokens/s':>9} {'x len':>6} "
          f"{'x size':>6} {'GFLOP/s':>8} {'% of matmul':>11}")
    rows, first = [], {}
    for preset in args.presets:
        model = build_model(preset, tok, seed=0).to(args.device)
        n_params = count_parameters(model)
        model.eval()
        for M in gen_lens:
            def engine(seed=0):
                return generate(model, tok, prompts, max_new_tokens=M, temperature=1.0, ignore_eos=True, seed=seed)

            engine()  # warm-up
            t = statistics.median(_timed(lambda: engine(r), args.device) for r in range(repeats))
            rows.append(dict(preset=preset, params=n_params, kind="generate", length=M, seconds=t,
                             tok_s=gen_batch * M / t, gflops=generation_flops(model, [prompt_len] * gen_batch, M) / t / 1e9))
        accelerator = loop.setup(0)
        optimizer = loop.build_optimizer(model, 1e-4)
        scheduler = loop.build_scheduler(optimizer, 0, 10 ** 6, "constant")
        g = torch.Generator().manual_seed(0)
        for T in train_lens:
            ids = torch.randint(3, len(tok), (train_batch, T), generator=g).to(args.device)
            batch = {"input_ids": ids, "attention_mask": torch.ones_like(ids)}

            def loss_fn(mb):
                logps, _ = sequence_logprobs(model, mb["input_ids"], mb["attention_mask"])  # (B, T), col 0 = 0
                return -logps.sum() / (train_batch * (T - 1)), {}

            def step():
                loop.optimizer_step(accelerator, model, optimizer, scheduler, [batch], loss_fn, 1.0, 0)

            step()  # warm-up
            t = statistics.median(_timed(step, args.device) for _ in range(repeats))
            rows.append(dict(preset=preset, params=n_params, kind="train", length=T, seconds=t,
                             tok_s=train_batch * T / t, gflops=training_flops(model, train_batch, T) / t / 1e9))
        del model, optimizer
        for r in rows:
            if r["preset"] != preset:
                continue
            first.setdefault((preset, r["kind"]), r["seconds"])
            r["x_length"] = r["seconds"] / first[(preset, r["kind"])]
            ref = next((q for q in rows if q["preset"] == args.presets[0] and q["kind"] == r["kind"]
                        and q["length"] == r["length"]), None)
            r["x_size"] = r["seconds"] / ref["seconds"]
            r["pct_of_matmul"] = 100 * r["gflops"] / peak
            print(f"{preset:<6} {n_params / 1e6:>6.1f}M {r['kind']:<8} {r['length']:>6} {r['seconds']:>8.3f} "
                  f"{r['tok_s']:>9.0f} {r['x_length']:>5.2f}x {r['x_size']:>5.2f}x {r['gflops']:>8.1f} "
                  f"{r['pct_of_matmul']:>10.1f}%", flush=True)
    if any(r["pct_of_matmul"] > 100 for r in rows):
        print("note: above 100% of the matmul rate means the matmul probe ran slower than the section (other load "
              "during the probe); rerun on an idle machine.")
    print(f"length = new tokens (generate) or tokens per row (train); tokens/s counts new tokens (generate) or all "
          f"tokens (train); x len = time / time at the shortest length, same preset; x size = time / "
          f"{args.presets[0]}'s at the same length.")
    return dict(matmul_gflops=peak, gen_batch=gen_batch, prompt_len=prompt_len, train_batch=train_batch, rows=rows)


# ------------------------------------------------------------------ section: real


def bench_real(args) -> dict:
    """A real instruct model (--real DIR, default models/smollm2-135m-instruct): the engine with fp32 and with
    bf16 weights (rollout.dtype) against fp32 `model.generate`, and one training step with and without bf16
    autocast (run.mixed_precision=bf16). Skipped, saying so, when the directory is missing."""
    from posttrain import chat
    from posttrain.models import is_model_dir
    from posttrain.tasks import wordmath

    if not is_model_dir(args.real):
        print(f"skipped: no model directory at {args.real} (posttrain models fetch smollm2-135m-instruct {args.real})")
        return {"skipped": str(args.real)}
    from posttrain.rollout import engine as eng
    from posttrain.runtime import native_bf16

    args.bf16_rows = args.real_bf16 == "yes" or (args.real_bf16 == "auto" and native_bf16())
    args.real_autocast = (False, True) if args.bf16_rows else (False,)  # the precisions of every row below: bf16?
    if not args.bf16_rows:
        print("bf16 rows skipped (--real-bf16 yes runs them): " + ("--real-bf16 no" if args.real_bf16 == "no" else
              "bf16 is not native and faster on this machine (runtime.native_bf16: run.mixed_precision=auto and "
              "rollout.dtype=auto run fp32 here)"))
    parts = set(args.real_parts)
    limits = real_limits(args)
    tok, model = _real_base(args)
    models = {"float32": model, "bfloat16": copy.deepcopy(model) if args.bf16_rows else None}
    weight_bytes = {"fp32": 4 * count_parameters(model), "bf16": 2 * count_parameters(model)}  # read per decode step
    out_all: dict = {"limits": limits}
    if "engine" not in parts:
        args.real_batches = []
    M = args.max_new_tokens
    print(f"{args.real}: {count_parameters(model) / 1e6:.1f}M parameters; prompts: word-math held-out problems "
          f"through the chat template; sampling at T=1, exactly {M} new tokens per row")
    rows_out = []
    if args.real_batches:
        print(f"{'batch':>5} {'generate tok/s':>15} {'engine fp32':>12} {'ratio':>7} {'engine bf16 w.':>15} "
              f"{'ratio':>7}")
    for B in args.real_batches:
        prompts = [r["prompt"] for r in wordmath.make_examples(B, 0, "eval")]
        batch = tok([chat.render_prompt(tok, p) for p in prompts], add_special_tokens=False, padding=True,
                    return_tensors="pt").to(args.device)

        def hf(seed=0):
            torch.manual_seed(seed)
            with torch.inference_mode():
                return model.generate(**batch, do_sample=True, temperature=1.0, top_k=0, top_p=1.0, max_new_tokens=M,
                                      min_new_tokens=M, pad_token_id=tok.pad_token_id, eos_token_id=tok.eos_token_id)

        def engine(dtype, seed=0):
            eng.configure(dtype=dtype)
            try:  # one model object per dtype: the engine caches one set of fused weights per model
                return generate(models[dtype], tok, prompts, max_new_tokens=M, temperature=1.0, ignore_eos=True,
                                seed=seed)
            finally:
                eng.configure()

        runners = {"model.generate": hf, "fp32": functools.partial(engine, "float32")}
        if args.bf16_rows:
            runners["bf16"] = functools.partial(engine, "bfloat16")
        for fn in runners.values():
            fn()  # warm-up, excluded
        times: dict[str, list[float]] = {k: [] for k in runners}
        for r in range(max(2, args.repeats // 2)):
            for k, fn in runners.items():
                times[k].append(_timed(lambda: fn(seed=r) if k != "model.generate" else fn(r), args.device))
        med = {k: statistics.median(v) for k, v in times.items()}
        row = {"batch": B, "new_tokens": M, **{f"{k}_tok_s": B * M / t for k, t in med.items()},
               **{f"ratio_{k}": med["model.generate"] / med[k] for k in ("fp32", "bf16") if k in med}, "times": times}
        rows_out.append(row)
        flops = generation_flops(model, [int(n) for n in batch["attention_mask"].sum(1)], M)
        for p, k in (("fp32", "fp32"), ("bf16", "bf16")):
            if k in med:  # each decode step streams every weight once: bytes x steps/s against the measured stream
                row[f"{k}_weight_gbs"] = weight_bytes[p] * M / med[k] / 1e9
                row[f"{k}_of_stream"] = row[f"{k}_weight_gbs"] / limits[p]["stream_gbs"]
                # and does 2 x parameters x batch FLOPs: past a few rows the matmul rate, not the stream, binds
                row[f"{k}_gflops"] = flops / med[k] / 1e9
                row[f"{k}_of_matmul"] = row[f"{k}_gflops"] / limits[p]["matmul_gflops"]
        bf16_cols = f"{row['bf16_tok_s']:>15.0f} {row['ratio_bf16']:>6.2f}x" if "bf16" in med else f"{'-':>15} {'-':>7}"
        frac = "  ".join(f"{k}: weights {row[f'{k}_weight_gbs']:.1f} GB/s = {100 * row[f'{k}_of_stream']:.0f}% of "
                         f"the stream, {row[f'{k}_gflops']:.0f} GFLOP/s = {100 * row[f'{k}_of_matmul']:.0f}% of the "
                         f"matmul rate" for k in ("fp32", "bf16") if f"{k}_weight_gbs" in row)
        print(f"{B:>5} {row['model.generate_tok_s']:>15.0f} {row['fp32_tok_s']:>12.0f} {row['ratio_fp32']:>6.2f}x "
              f"{bf16_cols}   {frac}", flush=True)
    if rows_out:
        print("ratio = model.generate time / engine time (medians of alternating runs; generate runs the fp32 model). "
              "GB/s: the engine's weight bytes (every parameter, in its dtype) x decode steps per second, against "
              "the weight-streaming bandwidth measured above; GFLOP/s: generation FLOPs (prefill, blocks, head and "
              "attention) per second against the matmul rate (prefill included in the time, so both slightly low).")
    out_all["rows"] = rows_out
    if "step" not in parts:
        out_all["trainers"] = _real_trainers(args, limits, parts)
        return out_all

    # one training step (forward + backward + AdamW) of the HF forward, fp32 and under bf16 autocast
    rows = wordmath.make_examples(8, 0, "train")
    texts = [chat.render_prompt(tok, r["prompt"]) + r["completion"].strip() + tok.eos_token for r in rows]
    enc = tok(texts, add_special_tokens=False, padding=True, return_tensors="pt").to(args.device)
    labels = enc["input_ids"].masked_fill(enc["attention_mask"] == 0, -100)
    train_model = copy.deepcopy(model).train()
    opt = torch.optim.AdamW(train_model.parameters(), lr=1e-6)
    losses = {}
    precisions = args.real_autocast
    with torch.no_grad():  # the same weights, both precisions: how far bf16 autocast moves the loss
        for a in precisions:
            with torch.autocast(args.device, dtype=torch.bfloat16, enabled=a):
                losses[a] = float(train_model(**enc, labels=labels).loss)

    def step(autocast: bool):
        with torch.autocast(args.device, dtype=torch.bfloat16, enabled=autocast):
            loss = train_model(**enc, labels=labels).loss
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)

    for a in precisions:
        step(a)  # warm-up
    t_step = {a: [] for a in precisions}
    for _ in range(max(2, args.repeats // 2)):
        for a in precisions:
            t_step[a].append(_timed(lambda: step(a), args.device))
    fp32_s = statistics.median(t_step[False])
    bf16_s = statistics.median(t_step[True]) if args.bf16_rows else None
    print(f"training step, batch 8 x {enc['input_ids'].shape[1]} tokens (HF forward + backward + AdamW): fp32 "
          f"{fp32_s:.2f} s" + (f", bf16 autocast {bf16_s:.2f} s ({fp32_s / bf16_s:.2f}x); loss of the same weights "
                               f"fp32 {losses[False]:.4f}, bf16 autocast {losses[True]:.4f}" if bf16_s else ""))
    n_tok = int(enc["attention_mask"].sum())
    print(f"  achieved (6N x {n_tok} non-pad tokens): fp32 {_of_peak(token_flops(model, n_tok), fp32_s, limits, 'fp32')}"
          + (f"; bf16 {_of_peak(token_flops(model, n_tok), bf16_s, limits, 'bf16')}" if bf16_s else ""))
    del train_model, opt
    gc.collect()
    return {**out_all, "train_step": {"tokens": int(enc["input_ids"].numel()), "fp32_s": fp32_s,
                                             "loss_fp32": losses[False], "loss_bf16": losses.get(True),
                                             "bf16_autocast_s": bf16_s, "speedup": fp32_s / bf16_s if bf16_s else None,
                                             "times": {"fp32": t_step[False], "bf16": t_step.get(True)}},
            "logprob_step": _real_logprob_step(args, model, limits),
            "trainers": _real_trainers(args, limits, parts)}


def _real_logprob_step(args, model, limits: dict) -> dict:
    """The policy update's forward + backward (`sequence_logprobs` of a GRPO-like batch: 2 prompts x 4 completions,
    60 prompt + 64 completion tokens) on the real model: the lean training forward against the HF forward, each
    fp32 and under bf16 autocast (what run.mixed_precision=bf16 gives the trainers), with how far each moves the
    log-probs from the fp32 lean path's."""
    from posttrain.lean import support
    from posttrain.logprobs import sequence_logprobs

    m = copy.deepcopy(model).train()
    g = torch.Generator().manual_seed(0)
    V = m.config.vocab_size
    prompt = torch.randint(10, V, (2, 60), generator=g).repeat_interleave(4, 0)
    ids = torch.cat([prompt, torch.randint(10, V, (8, 64), generator=g)], 1).to(args.device)
    am = torch.ones_like(ids)
    cm = am.clone()
    cm[:, :60] = 0
    lps: dict = {}

    def step(lean: bool, bf16: bool):
        was = support.ENABLED
        support.ENABLED = lean
        try:
            m.zero_grad(set_to_none=True)
            with torch.autocast(args.device, dtype=torch.bfloat16, enabled=bf16):
                lp, _ = sequence_logprobs(m, ids, am, cm)
            lp.sum().backward()
            lps[(lean, bf16)] = lp.detach()
        finally:
            support.ENABLED = was

    variants = [(lean, bf16) for bf16 in args.real_autocast for lean in (False, True)]
    for v in variants:
        step(*v)  # warm-up
    times: dict = {v: [] for v in variants}
    for _ in range(max(2, args.repeats // 2)):
        for v in variants:
            times[v].append(_timed(lambda: step(*v), args.device))
    med = {v: statistics.median(t) for v, t in times.items()}
    ref = lps[(True, False)]
    print(f"policy log-prob forward + backward, 8 rows x {ids.shape[1]} tokens (sequence_logprobs):")
    out = {}
    for lean, bf16 in variants:
        name = f"{'lean' if lean else 'HF'} {'bf16 autocast' if bf16 else 'fp32'}"
        err = float((lps[(lean, bf16)] - ref).abs().max())
        print(f"  {name:<18} {med[(lean, bf16)]:6.2f} s   max |log-prob - lean fp32's| {err:.2e}   "
              f"{_of_peak(token_flops(model, float(am.sum()), float(cm.sum())), med[(lean, bf16)], limits, 'bf16' if bf16 else 'fp32')}")
        out[name] = {"s": med[(lean, bf16)], "times": times[(lean, bf16)], "max_abs_logprob_diff": err}
    del m
    gc.collect()
    return out


def _real_trainers(args, limits: dict, parts: set) -> dict:
    """One SFT, DPO and GRPO step of ours against TRL's on the real model, fp32 and under bf16 (see the setups), and
    the multi-turn GRPO step with the calculator (`parts`: "trainers", "tools")."""
    out: dict = {}
    if "trainers" not in parts:
        return _real_tools(args, out, parts)
    repeats = 1 if args.quick else 2
    print(f"\n{'stage (real model)':<34} {'precision':>9} {'TRL s/step':>11} {'posttrain':>10} {'ratio':>7}")

    def row(stage, precision, mt, mo, extra=None):
        print(f"{stage:<34} {precision:>9} {mt:>11.3f} {mo:>10.3f} {mt / mo:>6.2f}x", flush=True)
        out.setdefault(stage, {})[precision] = dict(trl_s_per_step=mt, ours_s_per_step=mo, ratio=mt / mo,
                                                    **(extra or {}))

    precisions = args.real_autocast
    stages = (("SFT", "rows", lambda a, **k: _sft_setup(a, rows=4, **k)),
              ("SFT", "rows", lambda a, **k: _sft_setup(a, rows=16, **k)),  # ~1.1k tokens a step
              ("RM", "pairs", _rm_setup), ("DPO", "pairs", _dpo_setup))
    for stage, unit, setup in stages:
        for bf16 in precisions:
            ctx = setup(args, real=True, bf16=bf16)
            if ctx.trl_error is not None:
                _trl_missing(ctx.trl_error)
                return out
            times = _alternate({"trl": ctx.runners["trl"], "posttrain": ctx.runners["posttrain"]}, repeats,
                               args.device)
            mt, mo = statistics.median(times["trl"]) / ctx.S, statistics.median(times["posttrain"]) / ctx.S
            label = f"{stage}, {ctx.B} {unit} x {ctx.tokens / (ctx.S * ctx.B):.0f} tok"
            p = "bf16" if bf16 else "fp32"
            row(label, p, mt, mo, dict(times=times, tokens=ctx.tokens, steps=ctx.S))
            # the policy's forward + backward over every token (SFT: the head at the loss's tokens; RM: a one-output
            # head, left out; DPO: chosen and rejected, the head everywhere); a reference forward, where a side runs
            # one each step, is on top
            head = {"SFT": (getattr(ctx, "loss_tokens", None) or 0) / ctx.S, "RM": 0.0}.get(stage)
            flops = token_flops(_real_base(args)[1], ctx.tokens / ctx.S, head)
            print(f"  achieved: ours {_of_peak(flops, mo, limits, p)}; TRL {_of_peak(flops, mt, limits, p)}",
                  flush=True)
            ctx.cleanup()

    def online(ctx, label, line, extra=lambda ctx: {}) -> None:
        """GRPO's and distill's rows: each side's timed steps of one run per precision (its first steps warm-up);
        `label(ctx)` names the row, `line(ctx, phases)` prints what else it measured, `extra(ctx)` stores it."""
        try:
            label = label(ctx)
            for bf16 in precisions:
                t_ours, phases = ctx.runners["posttrain"](bf16=bf16)
                t_trl = ctx.runners["trl"](bf16=bf16)
                row(label, "bf16" if bf16 else "fp32", statistics.median(t_trl), statistics.median(t_ours),
                    dict(ours_times=t_ours, trl_times=t_trl, ours_phases=phases, **extra(ctx)))
                print(line(ctx, phases), flush=True)
        finally:
            ctx.cleanup()

    online(_grpo_setup(args, real=True), lambda ctx: f"GRPO, 2 x {ctx.group} x <= {args.max_new_tokens} tok",
           lambda ctx, ph: f"  completion tokens per row: posttrain {ph['completion_tokens']:.1f}, TRL "
                           f"{ctx.trl_completion_tokens:.1f}; posttrain sample {ph['sample']:.2f} s, update "
                           f"{ph['train']:.2f} s",
           lambda ctx: {"trl_completion_tokens": ctx.trl_completion_tokens})
    online(_distill_setup(args, real=True), lambda ctx: f"distill, {ctx.per_step} x <= {args.max_new_tokens} tok",
           lambda ctx, ph: f"  posttrain: {ph['completion_tokens']:.1f} completion tokens per row, sample "
                           f"{ph['sample']:.2f} s, teacher + update {ph['train']:.2f} s (reverse KL over the "
                           f"vocabulary; TRL beta 1)")
    print("ratio = TRL time per step / posttrain time per step; same model, rows, batch and settings. bf16: autocast "
          "over fp32 weights on both sides (GRPO and distill: ours also samples with bf16 weights, "
          "rollout.dtype=bfloat16; TRL generates under its autocast).")
    return _real_tools(args, out, parts)


def _real_tools(args, out: dict, parts: set) -> dict:
    """The multi-turn GRPO rows of the real section (the tools section's step on the real model), into `out`."""
    if "tools" not in parts:
        return out
    precisions = args.real_autocast

    def row(stage, precision, mt, mo):
        print(f"\n{'stage (real model)':<34} {'precision':>9} {'TRL s/step':>11} {'posttrain':>10} {'ratio':>7}")
        print(f"{stage:<34} {precision:>9} {mt:>11.3f} {mo:>10.3f} {mt / mo:>6.2f}x", flush=True)

    sft_dir, sft_s, sft_root = _real_tools_sft(args)
    lim = REAL_TOOL_LIMITS
    try:
        for bf16 in precisions:
            p = "bf16" if bf16 else "fp32"
            print(f"\nmulti-turn GRPO with the calculator, {p}: the real model after a short tool-use SFT "
                  f"({sft_s:.0f} s, untimed), calc-words (word-calc's held-out problems), 2 prompts x 8 episodes, "
                  f"<= {lim['max_turns']} turns x {lim['max_turn_tokens']} tokens, <= {lim['max_total_tokens']} in "
                  "all, lr 1e-7 (the episodes stay alike over a run), first 2 steps of each run excluded", flush=True)
            ctx = _tools_setup(args, real=True, bf16=bf16, sft_dir=sft_dir)
            r = _run_tools(ctx, args, "posttrain grpo grpo.env=calc-words", p)
            out.setdefault("tools", {})[p] = r
            if "trl_s_per_step" in r:
                row("multi-turn GRPO, 2 x 8 episodes", p, r["trl_s_per_step"], r["ours_s_per_step"])
    finally:
        shutil.rmtree(sft_root, ignore_errors=True)
        _REAL.pop("tools_sft", None)
    return out


# ------------------------------------------------------------------ section: multiturn


def bench_multiturn(args) -> dict:
    """Multi-turn episodes (posttrain.rollout.multiturn) against single-turn rollouts of the same sampled tokens."""
    from posttrain.chat import encode_prompts
    from posttrain.rollout.multiturn import generate_episodes
    from posttrain.tasks import calc as calc_task
    from posttrain.verifiers.envs import Environment, Limits, ToolCall
    from posttrain.verifiers.envs.calc import CalcEnv, calculator

    class EveryTurnCalls(Environment):  # each turn that ends at eos computes something; at most 4 turns
        name = "bench"
        tools = (calculator,)
        limits = Limits(max_turns=4, max_turn_tokens=32, max_total_tokens=256)

        def parse_calls(self, text, episode=None):
            return [ToolCall("calculator", {"expression": f"{len(text)}*{len(episode.turns)}+7"}, text)]

        def reward(self, episode):
            return 0.0

    tok = train_tokenizer(calc_task.corpus(300, 0), vocab_size=512, split_digits=True, chat=True)
    model = build_model(args.presets[0], tok, seed=0).eval()
    env = EveryTurnCalls()
    problems = CalcEnv.problems(max(args.batches), seed=1)
    firsts = encode_prompts(tok, [env.reset(p) for p in problems])
    with torch.no_grad():  # eos along the prompts' mean final state: turns end after a few to ~30 tokens
        h = torch.cat([model.model(input_ids=torch.tensor([x])).last_hidden_state[0] for x in firsts]).mean(0)
        model.lm_head.weight[tok.eos_token_id] = 0.45 * h / h.norm()
    rows_out = []
    print(f"\n{args.presets[0]}, calculator environment (every turn that ends at eos calls it; <= 4 turns x 32 tokens)")
    print(f"{'batch':>5} {'turns':>6} {'sampled':>8} {'env tok':>8} {'episodes s':>11} {'single-turn s':>14} "
          f"{'ratio':>7} {'steps ratio':>12} {'tool s':>7}")
    for B in args.batches:
        ps = problems[:B]

        def episodes(seed=0):
            return generate_episodes(model, tok, env, ps, n=1, seed=seed)

        out = episodes()
        sampled = sum(sum(r.completion_mask) for r in out)
        env_tokens = sum(len(r.completion_ids) for r in out) - sampled
        per_row = max(1, round(sampled / B))

        def single(seed=0):
            return generate(model, tok, firsts[:B], max_new_tokens=per_row, ignore_eos=True, seed=seed)

        single()
        t_ep, t_one = [], []
        for r in range(args.repeats):
            t_ep.append(_timed(lambda: episodes(0), "cpu"))
            t_one.append(_timed(lambda: single(0), "cpu"))
        med_ep, med_one = statistics.median(t_ep), statistics.median(t_one) * sampled / (per_row * B)
        turns = sum(len(r.extras["episode"]["turns"]) for r in out) / B
        tool_s = sum(c["seconds"] for r in out for t in r.extras["episode"]["turns"] for c in t["tool_calls"])
        row = dict(batch=B, turns=turns, sampled=sampled, env_tokens=env_tokens, episodes_s=med_ep,
                   single_s=med_one, ratio=med_ep / med_one, steps_ratio=(sampled + env_tokens) / sampled,
                   tool_s=tool_s, episodes_times=t_ep, single_times=t_one)
        rows_out.append(row)
        print(f"{B:>5} {turns:>6.2f} {sampled:>8} {env_tokens:>8} {med_ep:>11.3f} {med_one:>14.3f} "
              f"{row['ratio']:>6.2f}x {row['steps_ratio']:>11.2f}x {tool_s:>7.3f}", flush=True)
    print("ratio = episodes time / single-turn time for the same sampled tokens (single-turn: ignore_eos, the mean "
          "sampled tokens per row, scaled to the episodes' exact count); steps ratio = (sampled + environment "
          "tokens) / sampled: the ratio expected when an environment token costs one decoding step, as it does "
          "here (fed beside the other rows' sampling), before tool time and turn bookkeeping.")
    return dict(rows=rows_out)


# ------------------------------------------------------------------ section: tools

# posttrain.chat.PRESET_CHAT_TEMPLATE plus an assistant message's structured `tool_calls`, each rendered after its
# content in the environments' call format (posttrain.verifiers.envs.format_tool_call: <tool_call>{"name": ...,
# "arguments": {...}}</tool_call>), before the eos. TRL needs a template that renders tool_calls (its
# supports_tool_calling check) and keeps a tool-calling turn as the model wrote it; our episodes keep the same turn
# as its text, which renders to the same string (checked in _tools_setup), so both sides see one token sequence.
# `tools=` is not rendered: the environment's system message already lists the tools, on both sides.
TOOL_CHAT_TEMPLATE = (
    "{%- for message in messages -%}"
    "{{ '<|' + message['role'] + '|>' + message['content'] }}"
    "{%- if message['role'] == 'assistant' -%}"
    "{%- if message['tool_calls'] is defined and message['tool_calls'] -%}"
    "{%- for call in message['tool_calls'] -%}"
    "{%- set f = call['function'] if call['function'] is defined else call -%}"
    "{{ '<tool_call>' + {'name': f['name'], 'arguments': f['arguments']} | tojson + '</tool_call>' }}"
    "{%- endfor -%}"
    "{%- endif -%}"
    "{{ eos_token }}"
    "{%- endif -%}"
    "{%- endfor -%}"
    "{%- if add_generation_prompt %}{{ '<|assistant|>' }}{% endif -%}"
)


# The real model's ChatML (SmolLM2's template: a default system message, `<|im_start|>ROLE\n...<|im_end|>\n`) plus
# an assistant message's structured `tool_calls` in the same call format, as TOOL_CHAT_TEMPLATE does for the preset.
CHATML_TOOL_TEMPLATE = (
    "{%- for message in messages -%}"
    "{%- if loop.first and messages[0]['role'] != 'system' -%}"
    "{{ '<|im_start|>system\nYou are a helpful AI assistant named SmolLM, trained by Hugging Face<|im_end|>\n' }}"
    "{%- endif -%}"
    "{{ '<|im_start|>' + message['role'] + '\n' + (message['content'] or '') }}"
    "{%- if message['role'] == 'assistant' and message['tool_calls'] is defined and message['tool_calls'] -%}"
    "{%- for call in message['tool_calls'] -%}"
    "{%- set f = call['function'] if call['function'] is defined else call -%}"
    "{{ '<tool_call>' + {'name': f['name'], 'arguments': f['arguments']} | tojson + '</tool_call>' }}"
    "{%- endfor -%}"
    "{%- endif -%}"
    "{{ '<|im_end|>\n' }}"
    "{%- endfor -%}"
    "{%- if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif -%}"
)


def tool_response_template(eos_token: str, anchor: str = "<|assistant|>") -> dict:
    """TRL's response parser for TOOL_CHAT_TEMPLATE (a transformers `response_template`, as TRL writes them for
    Qwen3 in trl.chat_template_utils): the assistant's text after `anchor` (the template's assistant header), each
    <tool_call>{json}</tool_call> a call, the content up to the eos."""
    return {"defaults": {"role": "assistant"}, "start_anchor": anchor,
            "fields": {"tool_calls": {"open": "<tool_call>", "close": "</tool_call>", "repeats": True,
                                      "content": "json", "transform": {"type": "function", "function": "{content}"}},
                       "content": {"close": eos_token, "content": "text"}}}


TOOLS_UNEQUAL = (
    "budgets: ours per turn (the environment's max_turn_tokens sampled tokens) and in all (max_total_tokens sampled + "
    "environment tokens, max_turns turns); TRL generation_kwargs max_new_tokens=max_turn_tokens per generate call, "
    "max_completion_length=max_total_tokens over every turn (a tool result that would pass it is dropped and the "
    "episode ends; the last turn is cut to fit), max_tool_calling_iterations=max_turns - 1",
    "a malformed call (not JSON, no </tool_call>): ours answers it with 'error: malformed ...' and the episode goes "
    "on; TRL's parser falls back to plain text, so the turn has no call and the episode ends there",
    "a tool error: ours returns 'error: ValueError: ...', TRL \"{'error': '...'}\" (different token counts)",
    "a turn cut at max_turn_tokens: ours ends the episode (finish 'length'); TRL runs a closed call in it if it has one",
    "decoding: ours keeps each row's KV cache across turns and feeds tool tokens beside the other rows' sampling; "
    "TRL calls generate again for the rows that called a tool, on their whole conversation (a new prefill per turn); "
    "ours runs the calls in its ToolRunner's threads (5 s timeout) while other rows decode, TRL one after another "
    "between generate calls",
    "prompt order: ours draws its prompts by seed, TRL's sampler shuffles its own way: different problems per step "
    "from the same 64, and different random streams, so each side's turns and tokens are printed",
    "chat template: TRL refuses the model's own template (supports_tool_calling: it drops tool_calls); both sides "
    "get its tool version (TOOL_CHAT_TEMPLATE for the preset, CHATML_TOOL_TEMPLATE for SmolLM2's ChatML), which "
    "renders our episodes exactly as the model's own did, and TRL's tokenizer a response_template "
    "(tool_response_template) that parses the calc call format",
)


REAL_TOOL_LIMITS = {"max_turns": 3, "max_turn_tokens": 64, "max_total_tokens": 256}  # calc-words in the real rows


def _real_tools_sft(args) -> tuple[Path, float, Path]:
    """The real model after a short LoRA SFT on word-calc's tool-use demonstrations (merged into a plain model; what
    tests/real checks teaches the call): `posttrain sft`, untimed, ~1 min; cached for the process. (model directory,
    its seconds, the temporary root to remove)"""
    if "tools_sft" not in _REAL:
        from posttrain.cli import main as posttrain_main

        root = Path(tempfile.mkdtemp(prefix="posttrain-bench-tools-sft-"))
        recipe = root / "sft.yaml"
        recipe.write_text(f"""# the real tools rows' SFT (scripts/bench.py --only real)
task: {{name: word-calc, n_train: 48, n_eval: 8}}
model: {{path: {Path(args.real).resolve()}, max_length: 512}}
lora: {{enabled: true}}
sft: {{max_steps: 12, batch_size: 4, lr: 1.0e-3, warmup_steps: 0, eval_every: 0, save_every: 0, final_eval_rows: 0}}
""")
        out = io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(out):
            rc = posttrain_main(["sft", "--recipe", str(recipe), f"run.output_dir={root / 'runs'}",
                                 f"run.threads={args.threads}", "run.quiet=true"])
        assert rc == 0, "posttrain sft failed: " + " | ".join(out.getvalue().strip().splitlines()[-3:])
        _REAL["tools_sft"] = (root / "runs" / "sft" / "sft" / "final", time.perf_counter() - t0, root)
    return _REAL["tools_sft"]


def _tools_setup(args, real: bool = False, bf16: bool = False, sft_dir: Path | None = None) -> SimpleNamespace:
    """One multi-turn GRPO step in the calc environment: `posttrain grpo` with grpo.env=calc (the trainer, through the
    CLI) against TRL's GRPOTrainer with the calculator as a tool (`tools=[calculator]`).

    The model: the tiny preset (random init, seed 0) with a chat tokenizer trained on tiny-calc text, as the multiturn
    section builds it, then `posttrain sft` on tiny-calc's tool-use demonstrations (--tools-sft-steps steps, batch 8,
    lr 3e-3; untimed, ~1 min) so that it calls the calculator: a random model never writes a <tool_call>, and its
    episodes would be single-turn on both sides. Both sides start from that SFT model, with TOOL_CHAT_TEMPLATE. It
    calls the tool in nearly every episode (10-20% of its calls malformed at temperature 1, in the runs made while
    writing this) but rarely copies the tool's result into its answer, so most rewards are 0: both sides' updates
    then run (same compute) with zero advantages, and the weights barely move, so the episodes stay alike over a run.
    Same 64 problems (CalcEnv.problems, two 3-digit numbers), prompts rendered to the same token ids (asserted), 2
    prompts x 8 episodes per step, <= 3 turns, 48 tokens a turn, 192 in all, temperature 1, the calc reward on both
    sides (TRL: a reward function applying CalcEnv.score to the last message), beta 0, one pass, lr 1e-4 constant,
    clipping 1.0, fp32, no gradient checkpointing, zero-variance groups trained (ours zero_variance=keep; TRL always).
    Time per step as in the grpo section: ours is metrics.jsonl's time/step, TRL's is between its on_step_begin and
    on_step_end (generation, tool calls and the update all happen inside the step); the first 2 steps of every run
    are warm-up. What could not be made equal: TOOLS_UNEQUAL, printed with the results.

    real=True: the real model after a short tool-use SFT (`sft_dir`, from `_real_tools_sft`), calc-words (word
    problems, REAL_TOOL_LIMITS), word-calc's first 64 held-out problems, CHATML_TOOL_TEMPLATE on both sides; bf16:
    ours run.mixed_precision=bf16 with rollout.dtype=bfloat16, TRL bf16=True (autocast, its generation included).
    Both sides' lr 1e-7 there, as in the real GRPO row, so the episodes do not change over a run."""
    from posttrain.chat import PRESET_CHAT_TEMPLATE, encode_prompts
    from posttrain.cli import main as posttrain_main
    from posttrain.models import load_model, load_tokenizer, save_model
    from posttrain.tasks import calc as calc_task
    from posttrain.verifiers.envs import format_tool_call
    from posttrain.verifiers.envs.calc import CalcEnv, WordCalcEnv, calculator

    root = Path(tempfile.mkdtemp(prefix="posttrain-bench-tools-"))
    if real:
        from posttrain.problems import env_problem
        from posttrain.tasks import wordcalc

        (steps, group), template, anchor, lr = (4, 8) if args.quick else (6, 8), CHATML_TOOL_TEMPLATE, \
            "<|im_start|>assistant\n", 1e-7
        env = WordCalcEnv(**REAL_TOOL_LIMITS)
        problems = [env_problem(r) for r in wordcalc.make_examples(64, 0, "eval")]
        base = load_model(sft_dir)
        env_line = f"  env: calc-words\n  env_options: {json.dumps(REAL_TOOL_LIMITS)}"
        model_line = f"model: {{path: {sft_dir}, max_length: 768, start_from: base}}"
        task_line = "task: {name: word-calc, n_train: 8, n_eval: 8}"
    else:
        (steps, group), template, anchor, lr = (8, 8) if args.quick else (14, 8), TOOL_CHAT_TEMPLATE, \
            "<|assistant|>", 1e-4
        env = CalcEnv()
        problems = CalcEnv.problems(64, seed=1)
        tok = train_tokenizer(calc_task.corpus(300, 0), vocab_size=512, split_digits=True, chat=True)
        tok.chat_template = template
        base = build_model("tiny", tok, seed=0)
        save_model(base, tok, root / "model")
        env_line = "  env: calc"
        model_line = f"model: {{path: {root / 'model'}, max_length: 512, chat_template: \"on\"}}"
        task_line = "task: {name: tiny-calc, n_train: 2000, n_eval: 8}"
    lim = env.limits
    (root / "problems.jsonl").write_text("".join(json.dumps(p) + "\n" for p in problems))
    recipe = root / "bench-tools.yaml"
    precision = "bf16" if bf16 else "no"
    recipe.write_text(f"""# multi-turn GRPO step benchmark (scripts/bench.py --only tools / --only real); tiny: SFT ~1 min, then GRPO
{task_line}
{model_line}
run: {{mixed_precision: {precision}}}
rollout: {{dtype: {"bfloat16" if bf16 else "float32"}}}
sft:
  max_steps: {args.tools_sft_steps}
  batch_size: 8
  warmup_steps: 10
  eval_every: 0
  save_every: 0
  final_eval_rows: 0
grpo:
{env_line}
  train_file: {root / 'problems.jsonl'}
  prompts_per_step: 2
  group_size: {group}
  max_new_tokens: {lim.max_total_tokens}
  zero_variance: keep
  lr: {lr:.1e}
  eval_every: 0
  eval_rows: 0
  final_eval_rows: 0
  save_every: 0
""")

    def cli(stage: str, *overrides: str) -> None:
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            rc = posttrain_main([stage, "--recipe", str(recipe), f"run.output_dir={root / 'runs'}",
                                 f"run.threads={args.threads}", "run.quiet=true", *overrides])
        assert rc == 0, f"posttrain {stage} failed: " + " | ".join(out.getvalue().strip().splitlines()[-3:])

    t0 = time.perf_counter()
    if not real:
        cli("sft")
        sft_dir = root / "runs" / "bench-tools" / "sft" / "final"
    ctx = SimpleNamespace(steps=steps, group=group, base=base, sft_seconds=time.perf_counter() - t0, trl_error=None,
                          runners={}, cleanup=lambda: shutil.rmtree(root, ignore_errors=True))

    def ours() -> tuple[list[float], dict[str, float]]:
        cli("grpo", f"max_steps={steps}")
        metrics = root / "runs" / "bench-tools" / "grpo" / "metrics.jsonl"
        times, phases = _cli_step_times(metrics, ("sample", "score", "train"))
        rows = [json.loads(l) for l in metrics.read_text().splitlines()]
        rows = [r for r in rows if "time/step" in r][2:]
        work = {k: statistics.mean(r[f"env/{k}"] for r in rows)
                for k in ("turns", "tool_calls", "valid_calls", "sampled_tokens", "env_tokens")}
        work["reward"] = statistics.mean(r["reward/mean"] for r in rows)
        return times, dict(phases, **work)

    ctx.runners["posttrain"] = ours
    try:
        from datasets import Dataset
        from transformers import TrainerCallback
        from trl import GRPOConfig as TRLConfig, GRPOTrainer
        from trl.chat_template_utils import supports_tool_calling
    except ImportError as e:
        ctx.trl_error = e
        return ctx
    printer = _trl_quiet()

    def trl_tokenizer():
        t = load_tokenizer(sft_dir)
        t.chat_template = template
        t.response_template = tool_response_template(t.eos_token, anchor)
        return t

    trl_tok = trl_tokenizer()
    preset = copy.deepcopy(trl_tok)
    preset.chat_template = PRESET_CHAT_TEMPLATE
    if real:
        preset.chat_template = load_tokenizer(args.real).chat_template  # the real model's own ChatML
    ctx.template_check = dict(preset=supports_tool_calling(preset), tools=supports_tool_calling(trl_tok))
    # the same prompt tokens on both sides, and a tool-calling turn that TRL renders from its parsed call (content "",
    # tool_calls) renders as our episode's text of that turn does
    first = [env.reset(p) for p in problems]
    ours_ids = encode_prompts(trl_tok, first)
    if real:  # the tool template renders our episodes' prompts as the model's own template does
        assert ours_ids == encode_prompts(preset, first), "CHATML_TOOL_TEMPLATE renders prompts differently"
    trl_ids = [trl_tok.apply_chat_template(m, tools=[calculator], add_generation_prompt=True, tokenize=True,
                                           return_dict=False) for m in first]
    assert ours_ids == trl_ids, "TRL's prompt token ids differ from ours"
    args_ = {"expression": problems[0]["expression"] if "expression" in problems[0] else
             problems[0]["meta"]["expression"]}
    as_text = first[0] + [{"role": "assistant", "content": format_tool_call("calculator", args_)},
                          {"role": "tool", "content": str(problems[0]["answer"])}]
    call = {"type": "function", "function": {"name": "calculator", "arguments": args_}}
    as_call = first[0] + [{"role": "assistant", "content": "", "tool_calls": [call]},
                          {"role": "tool", "name": "calculator", "content": str(problems[0]["answer"])}]
    assert trl_tok.apply_chat_template(as_text, tokenize=False, add_generation_prompt=True) == \
        trl_tok.apply_chat_template(as_call, tokenize=False, add_generation_prompt=True), \
        "TOOL_CHAT_TEMPLATE renders TRL's tool-calling turn differently from our episode's"
    ctx.prompt_tokens = statistics.mean(len(x) for x in ours_ids)

    def calc_reward(completions, answer, **kwargs):
        # the calc environment's rule; the episode ended with an answer when its last message is an assistant turn
        # without calls (else TRL stopped it at max_tool_calling_iterations or at the token budget)
        out = []
        for messages, a in zip(completions, answer):
            last = messages[-1] if messages else {}
            finish = "answer" if last.get("role") == "assistant" and not last.get("tool_calls") else "max_turns"
            out.append(env.score({"answer": a}, last.get("content") or "", finish)[0])
        return out

    dataset = Dataset.from_list([{"prompt": m, "answer": p["answer"]} for m, p in zip(first, problems)])

    class StepProbe(TrainerCallback):
        """Each step's time, TRL's logged tool-call counts (its metric store) and, from the step's batch (TRL keeps it
        in _buffered_inputs: completion_mask over every completion token, tool_mask 0 on tool tokens), sampled and
        tool tokens and turns (runs of sampled tokens) per episode."""

        def __init__(self):
            self.times, self.rows, self.t0, self.trainer = [], [], 0.0, None

        def on_step_begin(self, *a, **k):
            self.t0 = time.perf_counter()

        def on_step_end(self, *a, **k):
            _sync(args.device)
            self.times.append(time.perf_counter() - self.t0)
            m = self.trainer._metrics["train"]
            calls, failed = (m[k][-1] if m.get(k) else 0.0 for k in ("tools/call_frequency", "tools/failure_frequency"))
            row = dict(tool_calls=calls, valid_calls=calls * (1 - failed), reward=m["reward"][-1])
            batch = self.trainer._buffered_inputs[0]
            completion = batch["completion_mask"].bool()  # (B, T)
            sampled = completion & batch["tool_mask"].bool()  # (B, T)
            turns = sampled[:, 0].long() + (sampled[:, 1:] & ~sampled[:, :-1]).sum(1)  # (B,)
            self.rows.append(dict(row, sampled_tokens=float(sampled.sum(1).float().mean()),
                                  env_tokens=float((completion & ~sampled).sum(1).float().mean()),
                                  turns=float(turns.float().mean())))

    def trl_run() -> tuple[list[float], dict[str, float]]:
        targs = TRLConfig(output_dir=str(root / "trl"), per_device_train_batch_size=2 * group, num_generations=group,
                          max_completion_length=lim.max_total_tokens,
                          generation_kwargs={"max_new_tokens": lim.max_turn_tokens},
                          max_tool_calling_iterations=lim.max_turns - 1, temperature=1.0, beta=0.0, num_iterations=1,
                          learning_rate=lr, lr_scheduler_type="constant", max_grad_norm=1.0, max_steps=steps,
                          bf16=bf16, fp16=False, **_no_checkpointing(), use_cpu=args.device == "cpu",
                          logging_strategy="no", save_strategy="no", report_to=[], disable_tqdm=True,
                          dataloader_num_workers=0, seed=0)
        probe = StepProbe()
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            trainer = GRPOTrainer(model=load_model(sft_dir), reward_funcs=[calc_reward], args=targs,
                                  train_dataset=dataset, processing_class=trl_tokenizer(), tools=[calculator],
                                  callbacks=[probe])
            trainer.remove_callback(printer)
            probe.trainer = trainer
            out = trainer.train()
        assert out.global_step == steps, f"TRL ran {out.global_step} steps, expected {steps}"
        assert not trainer.args.gradient_checkpointing, "TRL ran with activation checkpointing"
        rows = probe.rows[2:]
        work = {k: statistics.mean(r[k] for r in rows) for k in rows[0]}
        return probe.times[2:], work

    ctx.runners["trl"] = trl_run
    return ctx


def bench_tools(args) -> dict:
    ctx = _tools_setup(args)
    print(f"tiny: {count_parameters(ctx.base) / 1e6:.2f}M parameters, SFT on tiny-calc tool-use demonstrations "
          f"({args.tools_sft_steps} steps, {ctx.sft_seconds:.0f} s, untimed); calc environment, 2 prompts x "
          f"{ctx.group} episodes per step, <= 3 turns x 48 tokens, <= 192 tokens in all; {ctx.steps} steps per run "
          f"({1 if args.quick else 2} run(s) each, first 2 steps excluded)")
    return dict(_run_tools(ctx, args, "posttrain grpo grpo.env=calc", "fp32"), sft_steps=args.tools_sft_steps,
                sft_seconds=ctx.sft_seconds)


def _run_tools(ctx, args, ours_label: str, precision: str) -> dict:
    """Alternate the two sides of a `_tools_setup`, print the step times, the per-episode work and the per-token
    ratio; TRL's refusal is printed instead of a ratio."""
    import traceback

    steps = ctx.steps
    rounds = 1 if args.quick else 2
    if ctx.trl_error is not None:
        _trl_missing(ctx.trl_error)
        t, work = ctx.runners["posttrain"]()
        print(f"ours: {statistics.median(t):.3f} s/step ({work})")
        ctx.cleanup()
        return dict(ours_s_per_step=statistics.median(t), ours_work=work)
    print(f"TRL's supports_tool_calling: the model's own chat template {ctx.template_check['preset']}, the tool "
          f"template {ctx.template_check['tools']}; prompts: the same {ctx.prompt_tokens:.0f} token ids on both sides "
          "(asserted)")
    t_ours, t_trl, w_ours, w_trl = [], [], [], []
    try:
        for _ in range(rounds):  # alternate, so drifting load hits both
            t, w = ctx.runners["posttrain"]()
            t_ours, w_ours = t_ours + t, w_ours + [w]
            t, w = ctx.runners["trl"]()
            t_trl, w_trl = t_trl + t, w_trl + [w]
    except (ValueError, TypeError, ImportError, RuntimeError, AttributeError, KeyError) as e:
        if not w_ours or w_trl:
            raise
        where = next((f"{f.filename.split('site-packages/')[-1]}:{f.lineno}" for f in
                      reversed(traceback.extract_tb(e.__traceback__)) if "site-packages" in f.filename), "?")
        why = f"{type(e).__name__} at {where}: {str(e).splitlines()[0] if str(e) else ''}"
        mo = statistics.median(t_ours)
        print(f"TRL's GRPOTrainer cannot run this tool-calling step here, so no ratio: {why}")
        print(f"{ours_label:<58} {mo:>7.3f} s/step")
        ctx.cleanup()
        return dict(ours_s_per_step=mo, ours_work=w_ours[0], trl_error=why)
    mo, mt = statistics.median(t_ours), statistics.median(t_trl)
    wo = {k: statistics.mean(w[k] for w in w_ours) for k in w_ours[0]}
    wt = {k: statistics.mean(w[k] for w in w_trl) for k in w_trl[0]}
    trl_label = f"TRL GRPOTrainer tools=[calculator] ({precision}, no grad. ckpt)"
    print(f"{'implementation':<58} {'s/step':>7} {'ratio':>7}")
    print(f"{trl_label:<58} {mt:>7.3f} {mt / mo:>6.2f}x")
    print(f"{ours_label:<58} {mo:>7.3f} {'1.00x':>7}")
    print(f"posttrain phases (medians): sample {wo['sample']:.3f} s, score {wo['score']:.3f} s, update "
          f"{wo['train']:.3f} s")
    print("per episode (means over the timed steps; TRL's turns: runs of sampled tokens in its completion, its valid "
          "calls: calls less those whose tool raised):")
    cols = ("turns", "tool_calls", "valid_calls", "sampled_tokens", "env_tokens", "reward")
    print(f"  {'':<10}" + "".join(f"{c.replace('_', ' '):>16}" for c in cols))
    for name, w in (("posttrain", wo), ("TRL", wt)):
        print(f"  {name:<10}" + "".join(f"{w[c]:>16.2f}" for c in cols))
    per_token = {k: t / (2 * ctx.group * (w["sampled_tokens"] + w["env_tokens"])) * 1e3
                 for k, t, w in (("posttrain", mo, wo), ("trl", mt, wt))}
    print(f"per completion token (sampled + environment; a rough correction for the sides' different episodes, as a "
          f"batch's cost follows its longest episode): TRL {per_token['trl']:.2f} ms, posttrain "
          f"{per_token['posttrain']:.2f} ms, ratio {per_token['trl'] / per_token['posttrain']:.2f}x")
    print("ratio = TRL time per step / posttrain time per step: same SFT model, problems, prompt tokens, group size, "
          "turn and token limits, reward. Not equal (the APIs differ):")
    for line in TOOLS_UNEQUAL:
        print(f"  - {line}")
    ctx.cleanup()
    return dict(steps_per_run=steps, rounds=rounds, ours_s_per_step=mo, trl_s_per_step=mt, ratio=mt / mo,
                ours_work=wo, trl_work=wt, ms_per_token=per_token, ratio_per_token=per_token["trl"] / per_token["posttrain"],
                ours_times=t_ours, trl_times=t_trl, template_check=ctx.template_check)


SECTIONS = {
    "generate": bench_generate,
    "sft": bench_sft,
    "rm": bench_rm,
    "dpo": bench_dpo,
    "ppo": bench_ppo,
    "grpo": bench_grpo,
    "distill": bench_distill,
    "scaling": bench_scaling,
    "microbatch": bench_microbatch,
    "multiturn": bench_multiturn,
    "tools": bench_tools,
    "real": bench_real,
}

# section -> its setup (shared data and models, `runners`: implementation -> workload), for --memory-probe
SETUPS = {
    "generate": _generate_setup,
    "sft": _sft_setup,
    "rm": _rm_setup,
    "dpo": _dpo_setup,
    "ppo": _ppo_setup,
    "grpo": _grpo_setup,
    "distill": _distill_setup,
}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="every section, fewer steps and repeats (< 3 min)")
    ap.add_argument("--only", action="append", choices=sorted(SECTIONS), help="run only these sections")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--presets", default="tiny,small", help="comma-separated model presets (generate, scaling)")
    ap.add_argument("--batches", default="1,16,64", help="comma-separated batch sizes (generate)")
    ap.add_argument("--max-new-tokens", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per implementation in generate "
                                                              "(default 5 quick, 9)")
    ap.add_argument("--dpo-batch", type=int, default=8, help="pairs per step in the dpo section (default 8)")
    ap.add_argument("--micro-tokens", type=int, default=1024,
                    help="padded tokens per micro-batch in the microbatch section (default 1024)")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory probes (fresh processes)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument("--real", type=Path, default=Path(__file__).resolve().parents[1] / "models" / "smollm2-135m-instruct",
                    help="model directory of the real section (default models/smollm2-135m-instruct)")
    ap.add_argument("--real-batches", default="1,16,32", help="comma-separated batch sizes (real)")
    ap.add_argument("--real-parts", default="engine,step,trainers,tools",
                    help="comma-separated parts of the real section: engine (tok/s, weight bandwidth), step (one "
                         "training step and the log-prob step), trainers (SFT, DPO, GRPO vs TRL), tools (multi-turn "
                         "GRPO with the calculator vs TRL); default all")
    ap.add_argument("--real-bf16", choices=["auto", "yes", "no"], default="auto",
                    help="the real section's bf16 rows: auto (only where bf16 is native and faster, as "
                         "run.mixed_precision=auto decides; emulated bf16 makes them 2-5x slower than fp32 and "
                         "triples the section's runtime), yes, no")
    ap.add_argument("--tools-sft-steps", type=int, default=200,
                    help="SFT steps that teach the tools section's tiny model to call the calculator (default 200)")
    ap.add_argument("--memory-probe", default=None, help=argparse.SUPPRESS)  # SECTION:IMPL, internal
    args = ap.parse_args(argv)
    args.argv = [a for a in argv]
    args.presets = [p for p in args.presets.split(",") if p]
    unknown = [p for p in args.presets if p not in PRESETS]
    if unknown:
        ap.error(f"unknown preset(s) {unknown}; choose from {sorted(PRESETS)}")
    args.batches = [int(b) for b in args.batches.split(",") if b]
    args.real_batches = [int(b) for b in args.real_batches.split(",") if b]
    args.real_parts = [p for p in args.real_parts.split(",") if p]
    bad = set(args.real_parts) - {"engine", "step", "trainers", "tools"}
    if bad:
        ap.error(f"--real-parts: unknown part(s) {sorted(bad)}; choose from engine, step, trainers, tools")
    args.repeats = args.repeats or (5 if args.quick else 9)
    torch.set_num_threads(args.threads)
    from transformers import logging as hf_logging

    hf_logging.set_verbosity_error()  # load reports ("score.weight newly initialized") and deprecation notes
    hf_logging.disable_progress_bar()  # "Writing model shards" when the setups save models
    if args.memory_probe:
        return _memory_probe(args.memory_probe, args)
    print(f"posttrain bench: torch {torch.__version__}, {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads, device {args.device}, {'quick' if args.quick else 'full'}; "
          f"load average {_load()}")
    t0 = time.perf_counter()
    results = {}
    for name in args.only or list(SECTIONS):
        print(f"\n== {name} ==")
        t_sec = time.perf_counter()
        results[name] = SECTIONS[name](args)
        results[name]["section_seconds"] = time.perf_counter() - t_sec
        print(f"({name}: {results[name]['section_seconds']:.0f} s)")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; load average {_load()}")
    if os.getloadavg()[0] > args.threads + 0.5:  # the bench's own threads count towards the load
        print("note: other processes were using the CPU; with shared cores, OpenMP threads stall at barriers "
              "and timings (both columns) swing widely. Rerun on an idle machine for stable ratios.")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(dict(threads=args.threads, device=args.device, quick=args.quick,
                                             torch=torch.__version__, sections=results), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
