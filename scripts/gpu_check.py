"""The GPU path, checked in one short run: on a CUDA machine (~7 minutes, `--budget-s`) the rollout engine against
`model.generate` (with its default cache and with the static cache that transformers compiles), one or two steps of
every stage through the CLI in bf16 (sft, rm, dpo, dpo loss_type=kto, ppo, grpo, distill, sft and dpo with LoRA,
sft and ppo with fp32 weights under bf16 autocast) and one SFT step under accelerate's FSDP2 config (recipes/launch/fsdp.yaml)
with one process; the peak GPU memory of each row; one table at the end.

    python scripts/gpu_check.py                     # CUDA: a SmolLM2-135M-shaped model (30 layers, d=576, GQA 9/3)
    python scripts/gpu_check.py --quick             # batch 16 only in the engine section
    python scripts/gpu_check.py --only engine       # or --only stages; --stages sft,ppo picks stage rows
    python scripts/gpu_check.py --model DIR         # a real model directory instead (e.g. `posttrain models fetch`)
    python scripts/gpu_check.py --dry               # CPU: the same code on the tiny preset, fp32, batch 16
    python scripts/gpu_check.py --json out.json     # every row as JSON too (rewritten after each row)

Rows
- `engine vs generate DTYPE B=N` (N = 16, 64, 256; bf16 and fp32 weights): sampling, 128 new tokens per row
  (ignore_eos), one warm-up call then one timed call each of `posttrain.rollout.generate` (one micro-batch of N rows)
  and `model.generate` (default cache, min_new_tokens=128); tokens/s of both, and the engine's recorded sampling
  log-probs against the trainer's recomputation (`collate_rollouts` + `logprobs.batched_logprobs`): fp32 passes at a
  max abs difference < 1e-3, bf16 at a mean abs difference < 0.05 (its mismatch KL estimate, the mean over tokens of
  sample_lp - trainer_lp, is reported).
- `static-cache generate DTYPE B=N`: `model.generate(cache_implementation="static")` (transformers compiles the
  decode step): one warm-up call (compilation; its seconds reported, not timed), then one timed call; tokens/s and
  engine / static. Compiling costs ~60 s per shape (H200, 2026-12-04), so the bf16 ones run right after the engine
  cell of their batch and the fp32 ones last, while the engine section's time budget (`--engine-budget-s`, 300 s
  on CUDA) lasts; the rest say "skipped: engine time budget".
- `greedy agreement DTYPE B=16`: engine vs `model.generate`, greedy, 128 new tokens, the same left-padded prompts:
  rows identical token for token (k/16), first tokens equal, mean common prefix, and for the rows that part, the
  reference's top-1 minus top-2 logit where they part. With random weights the top two logits are often close, so
  bf16 rounding flips later tokens: fp32 passes at >= 15/16 identical rows, bf16 when every row is identical up to
  its first near-tie (a margin below GREEDY_TIE = 0.5 logits).
- one row per stage: a CLI subprocess (`posttrain STAGE --recipe ...`, 1-2 steps, no evals); a stage that needs
  an earlier one (dpo: sft and prefs; ppo: sft, prefs, rm; distill: a grpo teacher) builds it through the CLI's
  own chaining in the same run directory, with 1 step (dotted overrides such as sft.max_steps=1). Independent
  chains run concurrently (`--jobs`), the rows of a chain one after another, each with a timeout (`--row-timeout-s`);
  a failed row shows the last line of its stderr and does not stop the others.

Peak memory: `torch.cuda.max_memory_allocated` of the engine section's process per row; for a CLI row, of its own
process: the CLI runs under this script's wrapper mode (`gpu_check.py --posttrain ARGS` = `posttrain ARGS`, then it
writes its process's peaks to the file named by GPU_CHECK_PEAK_MEMORY), so nothing in the library changes. On CPU the
column shows the process's peak RSS instead.

Order: the stage rows first (the correctness checks), then the engine section with the time left, in a child
process of this script (a hung compilation is killed 60 s past its budget). The whole run keeps to `--budget-s`
(default 450 s on CUDA; `scripts/gpu_run.sh` runs it under `timeout 480`, and a SIGTERM still prints the table),
and rows it had no time for say so (FAILED). Exit status 0 only when every row is ok or skipped.

Needs only torch, transformers, accelerate and peft beside this project (no vLLM, no DeepSpeed). The GPU
machines reach no network, so by default the model is SmolLM2-135M-Instruct's architecture with random weights and
a tokenizer trained on the task (the speed and agreement checks do not need trained weights; its vocabulary is the
task tokenizer's, 4096, not 49k).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SCRIPT = Path(__file__).resolve()
PEAK_ENV = "GPU_CHECK_PEAK_MEMORY"  # read by this script's --posttrain wrapper only; the library never sees it
CHILD_ENV: dict[str, str] = {}  # added to every child's environment (--dry: CUDA_VISIBLE_DEVICES="", a CPU run anywhere)

SMOL = dict(hidden_size=576, intermediate_size=1536, num_hidden_layers=30, num_attention_heads=9,
            num_key_value_heads=3, max_position_embeddings=2048, tie_word_embeddings=True, rope_theta=100000.0)
NEW_TOKENS = 128  # per row, every engine-section call
DTYPE_NAMES = {"bfloat16": "bf16", "float32": "fp32"}


def build_model(out: Path, dry: bool) -> Path:
    """A model directory: the tiny preset (dry) or SmolLM2-135M's shape, random init, task-trained tokenizer."""
    import torch
    from transformers import LlamaConfig, LlamaForCausalLM

    from posttrain import tasks
    from posttrain.models import bootstrap

    corpus = tasks.get_task("tiny-summarize").corpus(300, 0)
    if dry:
        bootstrap("tiny", corpus, out, vocab_size=512, seed=0, max_length=256)
        return out
    _, tok = bootstrap("tiny", corpus, out, vocab_size=4096, seed=0, max_length=512)
    cfg = LlamaConfig(vocab_size=len(tok), pad_token_id=tok.pad_token_id, eos_token_id=tok.eos_token_id,
                      bos_token_id=tok.bos_token_id, **SMOL)
    torch.manual_seed(0)
    LlamaForCausalLM(cfg).save_pretrained(out)
    return out


# ============================================================================ engine section (a child process)
def engine_plan(dtypes: list[str], batches: list[int], cuda: bool) -> list[tuple[str, str, int]]:
    """(kind, dtype, batch) in the order they run: the greedy checks, then per batch the first dtype's (bf16 on
    CUDA) sampling cell and its static-cache cell (the comparison that matters: one compilation each, ~60 s),
    the other dtypes' sampling cells, and last the other dtypes' static-cache cells."""
    first, rest = dtypes[0], dtypes[1:]
    plan = [("greedy", dt, 16) for dt in dtypes]
    for b in batches:
        plan += [("sample", first, b), ("static", first, b)] + [("sample", dt, b) for dt in rest]
    plan += [("static", dt, b) for dt in rest for b in batches]
    return plan


# Greedy rows in half precision may part from model.generate only where its top-1 and top-2 logits are this close:
# bf16 logits of a 30-layer model differ from another bf16 forward's by ~0.03 of their scale (lean vs HF, measured
# in tests/posttrain/rollout/test_half_precision.py), a few tenths of a logit at SmolLM2's scale.
GREEDY_TIE = 0.5


def engine_row_name(kind: str, dt: str, b: int) -> str:
    return {"sample": "engine vs generate", "static": "static-cache generate",
            "greedy": "greedy agreement"}[kind] + f" {DTYPE_NAMES.get(dt, dt)} B={b}"


def _left_pad(tok, ids: list[list[int]]):
    import torch

    T = max(map(len, ids))
    x = torch.full((len(ids), T), tok.pad_token_id, dtype=torch.long)
    am = torch.zeros_like(x)
    for i, p in enumerate(ids):
        x[i, T - len(p):], am[i, T - len(p):] = torch.tensor(p), 1
    return x, am


class EngineSection:
    """The engine rows, each a dict; `run` calls `emit(name, row)` after each (the worker writes them out)."""

    def __init__(self, model_dir: Path, device: str, dtypes: list[str], batches: list[int], budget_s: float):
        import torch

        from posttrain.chat import encode_prompts
        from posttrain.models import load_tokenizer
        from posttrain.tasks import summarize

        self.torch, self.device, self.cuda = torch, device, device.startswith("cuda")
        self.model_dir, self.dtypes, self.batches, self.budget_s = model_dir, dtypes, batches, budget_s
        self.tok = load_tokenizer(model_dir)
        self.prompts = [r["prompt"] for r in summarize.make_examples(max(batches + [16]), 0, "eval")]
        self.ids = encode_prompts(self.tok, self.prompts)
        self.models: dict[str, object] = {}
        self.engine_tps: dict[tuple[str, int], float] = {}
        self.t0 = time.time()

    # ---- helpers
    def model(self, dt: str):
        if dt not in self.models:
            from posttrain.models import load_model

            self.models[dt] = load_model(self.model_dir, getattr(self.torch, dt), device=self.device).eval()
        return self.models[dt]

    def sync(self) -> None:
        if self.cuda:
            self.torch.cuda.synchronize()

    def timed(self, fn):
        self.sync()
        t = time.time()
        out = fn()
        self.sync()
        return out, time.time() - t

    def reset_peak(self) -> None:
        if self.cuda:
            self.torch.cuda.empty_cache()
            self.torch.cuda.reset_peak_memory_stats()

    def peak(self) -> dict:
        if self.cuda:
            return {"peak_mb": round(self.torch.cuda.max_memory_allocated() / 2**20)}
        import resource  # CPU: the process's peak RSS so far

        return {"peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}

    def hf_generate(self, model, b: int, *, greedy: bool, static: bool = False, margins: list | None = None
                    ) -> list[list[int]]:
        """`model.generate` on the first b prompts, left-padded; the new tokens of each row. `margins` (greedy): filled
        with each row's top-1 minus top-2 logit at every step, (b, steps)."""
        x, am = _left_pad(self.tok, self.ids[:b])
        kw = dict(max_new_tokens=NEW_TOKENS, pad_token_id=self.tok.pad_token_id, eos_token_id=self.tok.eos_token_id)
        if greedy:
            kw.update(do_sample=False)
        else:  # plain sampling at temperature 1 (no top-k: transformers' default is 50), every row 128 tokens
            kw.update(do_sample=True, temperature=1.0, top_k=0, top_p=1.0, min_new_tokens=NEW_TOKENS)
        if static:
            kw["cache_implementation"] = "static"
        if margins is not None:
            kw.update(output_scores=True, return_dict_in_generate=True)
        with self.torch.no_grad():
            out = model.generate(x.to(self.device), attention_mask=am.to(self.device), **kw)
        if margins is not None:
            top2 = self.torch.stack([s.float().topk(2, -1).values for s in out.scores], 1)  # (b, steps, 2)
            margins.extend((top2[..., 0] - top2[..., 1]).tolist())
            out = out.sequences
        return out[:, x.shape[1]:].tolist()

    def engine(self, model, b: int, *, greedy: bool, seed: int = 0):
        from posttrain.rollout import generate

        longest = max(len(p) for p in self.ids[:b])
        kw = dict(max_new_tokens=NEW_TOKENS, seed=seed, max_batch_tokens=b * (longest + NEW_TOKENS))  # one micro-batch
        kw.update(greedy=True) if greedy else kw.update(temperature=1.0, ignore_eos=True)
        return generate(model, self.tok, self.prompts[:b], **kw)

    # ---- rows
    def sample_row(self, dt: str, b: int) -> dict:
        from posttrain.logprobs import batched_logprobs
        from posttrain.rollout import collate_rollouts

        model = self.model(dt)
        self.reset_peak()
        self.engine(model, b, greedy=False, seed=1)  # warm-up (kernels, allocator), not timed
        outs, t = self.timed(lambda: self.engine(model, b, greedy=False))
        row: dict = {"status": "ok", **self.peak()}
        tokens = sum(len(o.completion_ids) for o in outs)
        tps = tokens / t
        self.engine_tps[(dt, b)] = tps
        row["engine tok/s"] = round(tps)
        if tokens != b * NEW_TOKENS:
            row["status"] = f"FAILED: the engine made {tokens} tokens, expected {b} x {NEW_TOKENS} (ignore_eos)"
        # the sampler's recorded log-probs against the trainer's recomputation of the same tokens
        batch = collate_rollouts(outs, self.tok.pad_token_id)
        trainer_lp, _ = batched_logprobs(model, batch, micro_batch_size=64)
        mask = batch.completion_mask > 0
        d = (batch.logprobs - trainer_lp.float().cpu())[mask]
        max_abs, mean_abs, kl = float(d.abs().max()), float(d.abs().mean()), float(d.mean())
        row.update({"logprob max abs diff": f"{max_abs:.2e}", "logprob mean abs diff": f"{mean_abs:.2e}",
                    "mismatch KL": f"{kl:.2e}"})
        bad = max_abs >= 1e-3 if dt == "float32" else not mean_abs < 0.05
        if bad and row["status"] == "ok":
            row["status"] = (f"FAILED: sampling log-probs differ from the trainer's: "
                             + (f"max abs {max_abs:.2e} >= 1e-3" if dt == "float32" else
                                f"mean abs {mean_abs:.2e} >= 0.05"))
        try:  # model.generate with its default cache: one warm-up, one timed call
            self.hf_generate(model, b, greedy=False)
            ref, t_hf = self.timed(lambda: self.hf_generate(model, b, greedy=False))
            hf_tps = sum(map(len, ref)) / t_hf
            row.update({"generate tok/s": round(hf_tps), "engine / generate": round(tps / hf_tps, 2)})
        except Exception as e:  # the engine's figures stay in the row
            if row["status"] == "ok":
                row["status"] = f"FAILED: model.generate: {type(e).__name__}: {e}"[:200]
        return row

    def static_row(self, dt: str, b: int) -> dict:
        model = self.model(dt)
        self.reset_peak()
        _, warm = self.timed(lambda: self.hf_generate(model, b, greedy=False, static=True))  # compiles
        ref, t = self.timed(lambda: self.hf_generate(model, b, greedy=False, static=True))
        tps = sum(map(len, ref)) / t
        row = {"status": "ok", **self.peak(), "static tok/s": round(tps), "warm-up s": round(warm, 1)}
        if (dt, b) in self.engine_tps:
            row["engine / static"] = round(self.engine_tps[(dt, b)] / tps, 2)
        return row

    def greedy_row(self, dt: str, b: int) -> dict:
        model = self.model(dt)
        self.reset_peak()
        ours = self.engine(model, b, greedy=True)
        margins: list = []
        ref = self.hf_generate(model, b, greedy=True, margins=margins)
        row: dict = {"status": "ok", **self.peak()}
        eos = self.tok.eos_token_id
        same = first = prefix = at_tie = 0
        worst = 0.0  # the largest reference margin at which a row parted from model.generate
        for o, r, m in zip(ours, ref, margins):
            r = r[:r.index(eos) + 1] if eos in r else r
            same += o.completion_ids == r
            first += bool(o.completion_ids) and bool(r) and o.completion_ids[0] == r[0]
            k = 0
            while k < min(len(o.completion_ids), len(r)) and o.completion_ids[k] == r[k]:
                k += 1
            prefix += k
            if o.completion_ids != r and k < len(m):
                worst = max(worst, m[k])
                at_tie += m[k] < GREEDY_TIE
        row.update({"greedy agreement": f"{same}/{b} rows", "parted at a near-tie": f"{at_tie}/{b - same}",
                    "largest margin where rows parted": round(worst, 3), "first tokens": f"{first}/{b}",
                    "mean common prefix": round(prefix / b, 1)})
        if dt == "float32" and same < b - 1:
            row["status"] = f"FAILED: greedy agreement {same}/{b} rows (fp32 needs >= {b - 1})"
        elif dt != "float32" and same + at_tie < b:
            row["status"] = (f"FAILED: {b - same - at_tie} row(s) parted from model.generate where its top-2 margin "
                             f"was >= {GREEDY_TIE} (not a {dt} rounding tie)")
        return row

    def run(self, emit) -> None:
        static_cost = 60.0  # a guess at one compilation until one is measured
        for kind, dt, b in engine_plan(self.dtypes, self.batches, self.cuda):
            name = engine_row_name(kind, dt, b)
            used = time.time() - self.t0
            if kind == "static":
                if not self.cuda:
                    emit(name, {"status": "skipped: needs CUDA"})
                    continue
                if used + static_cost > self.budget_s:
                    emit(name, {"status": f"skipped: engine time budget ({self.budget_s:.0f} s; one compilation "
                                          f"took ~{static_cost:.0f} s)"})
                    continue
            elif used > self.budget_s:
                emit(name, {"status": f"FAILED: not run: the engine time budget ({self.budget_s:.0f} s) was spent"})
                continue
            t = time.time()
            try:
                row = {"sample": self.sample_row, "static": self.static_row, "greedy": self.greedy_row}[kind](dt, b)
            except Exception as e:  # a row that fails is reported; the others still run
                row = {"status": f"FAILED: {type(e).__name__}: {e}"[:240]}
            row["seconds"] = round(time.time() - t, 1)
            if kind == "static":
                static_cost = max(time.time() - t, 5.0)
            emit(name, row)


def engine_worker(spec_file: str) -> int:
    """`gpu_check.py --engine-worker SPEC.json`: the engine section in its own process; writes the rows into
    spec["out"] after each row."""
    spec = json.loads(Path(spec_file).read_text())
    import torch

    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    rows: dict[str, dict] = {}

    def emit(name: str, row: dict) -> None:
        rows[name] = row
        tmp = Path(spec["out"] + ".tmp")
        tmp.write_text(json.dumps(rows))
        tmp.replace(spec["out"])
        print(f"[gpu_check] {name}: {row}", flush=True)

    EngineSection(Path(spec["model_dir"]), spec["device"], spec["dtypes"], spec["batches"],
                  spec["budget_s"]).run(emit)
    return 0


# ============================================================================ stage rows (CLI subprocesses)
def posttrain_with_peak(args: list[str]) -> int:
    """`gpu_check.py --posttrain ARGS`: `posttrain ARGS`, then this process's peak memory into $GPU_CHECK_PEAK_MEMORY
    (also when the stage raised). Works under `accelerate launch` too (a script it can run)."""
    from posttrain.cli import main as cli_main

    try:
        return cli_main(args)
    finally:
        path = os.environ.get(PEAK_ENV)
        if path:
            import resource

            import torch

            peak = {"max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}
            if torch.cuda.is_available() and torch.cuda.is_initialized():
                peak["cuda_peak_mb"] = round(torch.cuda.max_memory_allocated() / 2**20)
            Path(path).write_text(json.dumps(peak))


SUMMARIZE, MATH = "tiny-summarize", "tiny-math"


def stage_settings(stage: str, steps: int) -> list[str]:
    """The smallest settings that run `steps` steps of a stage (no evaluations, no intermediate checkpoints)."""
    return {
        "sft": [f"max_steps={steps}", "batch_size=8", "eval_every=0", "final_eval_rows=0", "save_every=0",
                "warmup_steps=0", "log_every=1"],
        "prefs": ["n_prompts=16", "n_eval_prompts=8", "samples_per_prompt=2", "max_new_tokens=16"],
        "rm": [f"max_steps={steps}", "batch_size=4", "eval_every=0", "save_every=0", "warmup_steps=0", "log_every=1"],
        "dpo": [f"max_steps={steps}", "batch_size=4", "online=false", "proxy_rm=none", "eval_every=0", "eval_rows=0",
                "final_eval_rows=0", "save_every=0", "warmup_steps=0", "log_every=1"],
        "ppo": [f"max_steps={steps}", "rollout_batch_size=8", "minibatch_size=4", "ppo_epochs=1", "max_new_tokens=16",
                "reward_norm_prompts=8", "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0",
                "log_every=1"],
        "grpo": [f"max_steps={steps}", "prompts_per_step=2", "group_size=4", "max_new_tokens=32",
                 "zero_variance=keep", "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0"],
        "distill": [f"max_steps={steps}", "prompts_per_step=2", "group_size=2", "max_new_tokens=16", "eval_every=0",
                    "eval_rows=0", "final_eval_rows=0", "save_every=0"],
    }[stage]


# id: (row label, recipe, stage, chain, extra overrides, earlier stages it may build). The rows of a chain share a
# run directory and run in this order, so later rows find the earlier stages' outputs.
STAGE_ROWS: dict[str, tuple[str, str, str, str, tuple[str, ...], tuple[str, ...]]] = {
    "sft": ("sft", SUMMARIZE, "sft", "summarize", (), ()),
    "rm": ("rm", SUMMARIZE, "rm", "summarize", (), ("sft", "prefs")),
    "dpo": ("dpo", SUMMARIZE, "dpo", "dpo", (), ("sft", "prefs")),
    "kto": ("dpo loss_type=kto", SUMMARIZE, "dpo", "dpo", ("loss_type=kto",), ("sft", "prefs")),
    "ppo": ("ppo", SUMMARIZE, "ppo", "summarize", (), ("sft", "prefs", "rm")),
    "grpo": ("grpo", MATH, "grpo", "math", ("model.start_from=base",), ()),
    "distill": ("distill (grpo teacher)", MATH, "distill", "math", ("model.start_from=base",), ("grpo",)),
    "sft-lora": ("sft LoRA", SUMMARIZE, "sft", "lora", ("lora.enabled=true",), ()),
    "dpo-lora": ("dpo LoRA", SUMMARIZE, "dpo", "lora", ("lora.enabled=true",), ("sft", "prefs")),
    "sft-autocast": ("sft fp32 weights + bf16 autocast", SUMMARIZE, "sft", "autocast",
                     ("model.dtype=float32", "run.mixed_precision=bf16"), ()),
    # PPO's bf16-weights row failed on an H200 (non-finite gradient at step 1, docs/results-archive.md, "The GPU
    # path"): the same chain in fp32 weights under autocast tells the weights' precision from the compute's
    "ppo-autocast": ("ppo fp32 weights + bf16 autocast", SUMMARIZE, "ppo", "autocast-ppo",
                     ("model.dtype=float32", "run.mixed_precision=bf16"), ("sft", "prefs", "rm")),
    "fsdp": ("sft FSDP2 1 process (fp32 weights, bf16)", SUMMARIZE, "sft", "fsdp", ("model.dtype=float32",), ()),
}
METRIC_KEYS = ("loss", "policy/loss", "reward/mean")  # the last value of each that a stage logs goes in its row


def stage_row_name(sid: str, dtype: str) -> str:
    label = STAGE_ROWS[sid][0]
    return label if sid in ("sft-autocast", "ppo-autocast", "fsdp") else f"{label} ({DTYPE_NAMES.get(dtype, dtype)})"


class Runner:
    """Subprocesses with timeouts, killed as a group; every one still alive is killed by `kill_all`."""

    def __init__(self):
        self.live: set[subprocess.Popen] = set()
        self.lock = threading.Lock()
        self.stopped = threading.Event()

    def run(self, cmd: list[str], cwd: Path, env: dict, timeout: float, log: Path) -> tuple[int | None, str]:
        with open(log.with_suffix(".out"), "w") as out, open(log.with_suffix(".err"), "w") as err:
            proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=err, start_new_session=True)
            with self.lock:
                self.live.add(proc)
            try:
                if self.stopped.is_set():
                    raise Stop()
                rc = proc.wait(timeout=max(timeout, 1))
            except subprocess.TimeoutExpired:
                self._kill(proc)
                rc = None
            except BaseException:  # Stop (SIGTERM) or Ctrl-C: no child outlives the check
                self._kill(proc)
                raise
            finally:
                with self.lock:
                    self.live.discard(proc)
        return rc, _last_line(log.with_suffix(".err")) or _last_line(log.with_suffix(".out"))

    def _kill(self, proc: subprocess.Popen) -> None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        proc.wait()

    def kill_all(self) -> None:
        self.stopped.set()
        with self.lock:
            procs = list(self.live)
        for p in procs:
            self._kill(p)


_ERROR_LINE = re.compile(r"^(posttrain: |[\w.]*(Error|Exception|Interrupt)\b)")


def _last_line(path: Path) -> str:
    """The line that says what went wrong: the last error line (`posttrain: ...`, `SomeError: ...`) of the output,
    else its last line that is not a rule of '=' / '-' (torchrun ends a failure with its own banner)."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    lines = [l.strip() for l in text.replace("\r", "\n").splitlines() if l.strip()]
    errors = [l for l in lines if _ERROR_LINE.match(l)]
    plain = [l for l in lines if l.strip("=-_ ")]
    return errors[-1] if errors else plain[-1] if plain else ""


def stage_command(sid: str, model_dir: Path, out: Path, dtype: str, threads: int, launch: list[str]) -> list[str]:
    _, recipe, stage, _, extra, earlier = STAGE_ROWS[sid]
    args = [stage, "--recipe", recipe, *stage_settings(stage, 2 if stage in ("sft", "rm", "dpo") else 1)]
    for e in earlier:  # an earlier stage this one builds when its output is missing: 1 step
        args += [f"{e}.{kv}" for kv in stage_settings(e, 1)]
    args += [f"model.path={model_dir}", f"model.dtype={dtype}", f"run.output_dir={out}", "run.quiet=true",
             f"run.threads={threads}", "task.n_train=64", "task.n_eval=8", "model.max_length=256", *extra]
    return [*launch, str(SCRIPT), "--posttrain", *args]


def stage_row(runner: Runner, sid: str, cmd: list[str], out: Path, timeout: float) -> dict:
    _, recipe, stage, _, _, _ = STAGE_ROWS[sid]
    if timeout < 5:
        return {"status": "FAILED: not run: the time budget was spent"}
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    peak_file = logs / f"{sid}.peak.json"
    env = {**os.environ, PEAK_ENV: str(peak_file), "PYTHONUNBUFFERED": "1", "TOKENIZERS_PARALLELISM": "false",
           **CHILD_ENV}
    t0 = time.time()
    rc, last = runner.run(cmd, ROOT, env, timeout, logs / sid)
    row: dict = {"seconds": round(time.time() - t0, 1)}
    try:
        peak = json.loads(peak_file.read_text())
        row["peak_mb" if "cuda_peak_mb" in peak else "peak_rss_mb"] = peak.get("cuda_peak_mb", peak["max_rss_mb"])
    except (OSError, ValueError, KeyError):
        pass
    if rc is None:
        return {"status": f"FAILED: timed out after {timeout:.0f} s (last line: {last[:120]})", **row}
    if runner.stopped.is_set() and rc < 0:
        return {"status": f"FAILED: stopped by a signal while running (last line: {last[:120]})", **row}
    if rc != 0:
        return {"status": f"FAILED (exit {rc}): {last[:200]}", **row}
    try:
        metrics = [json.loads(l) for l in (out / recipe / stage / "metrics.jsonl").read_text().splitlines() if l]
        steps = [m for m in metrics if any(k in m for k in METRIC_KEYS)]
        if not steps:
            raise ValueError("none")
        row["steps"] = len(steps)
        for key in METRIC_KEYS:
            values = [m[key] for m in steps if key in m]
            if values:
                row[key] = round(float(values[-1]), 4)
    except (OSError, ValueError) as e:
        return {"status": f"FAILED: exit 0 but no step metrics in {recipe}/{stage}/metrics.jsonl ({e})"[:200], **row}
    return {"status": "ok", **row}


# ============================================================================ main
class Report:
    """The rows in table order; rewrites the JSON file after every change."""

    def __init__(self, names: list[str], env: dict, json_path: Path | None):
        self.rows: dict[str, dict] = {n: {"status": "FAILED: not run (the check stopped first)"} for n in names}
        self.env, self.json_path, self.lock = env, json_path, threading.Lock()

    def set(self, name: str, row: dict, say: bool = True) -> None:
        with self.lock:
            self.rows[name] = row
            self.save()
        if say:
            print(f"[gpu_check] {name}: {row['status']}", flush=True)

    def save(self) -> None:
        if self.json_path:
            tmp = self.json_path.with_name(self.json_path.name + ".tmp")
            tmp.write_text(json.dumps({"env": self.env, "rows": self.rows}, indent=1))
            tmp.replace(self.json_path)

    def ok(self) -> bool:
        return all(r["status"] == "ok" or r["status"].startswith("skipped") for r in self.rows.values())

    def table(self) -> str:
        lines = ["| row | status | figures | peak memory |", "|---|---|---|---|"]
        for name, r in self.rows.items():
            figures = ", ".join(f"{k} {v}" for k, v in r.items() if k not in ("status", "peak_mb", "peak_rss_mb"))
            peak = f"{r['peak_mb']} MiB" if "peak_mb" in r else f"{r['peak_rss_mb']} MiB RSS" if "peak_rss_mb" in r \
                else ""
            lines.append(f"| {name} | {r['status']} | {figures} | {peak} |")
        return "\n".join(lines)


def versions(cuda: bool) -> dict:
    import platform

    import accelerate
    import peft
    import torch
    import transformers

    return {"device": torch.cuda.get_device_name(0) if cuda else "cpu", "torch": torch.__version__,
            "cuda": torch.version.cuda, "transformers": transformers.__version__,
            "accelerate": accelerate.__version__, "peft": peft.__version__, "python": platform.python_version()}


class Stop(Exception):
    """SIGTERM (e.g. `timeout`): stop, kill the children, still print the table and write the JSON."""


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["--posttrain"]:
        return posttrain_with_peak(argv[1:])
    if argv[:1] == ["--engine-worker"]:
        return engine_worker(argv[1])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dry", action="store_true", help="CPU: tiny preset, fp32, batch 16, no FSDP/static cache")
    ap.add_argument("--model", type=Path, help="a model directory instead of the SmolLM2-shaped random model")
    ap.add_argument("--json", type=Path, help="write every row here too (rewritten after each row)")
    ap.add_argument("--only", choices=["engine", "stages"], help="run one section")
    ap.add_argument("--stages", help=f"comma-separated stage rows (default all): {','.join(STAGE_ROWS)}")
    ap.add_argument("--quick", action="store_true", help="engine section at batch 16 only")
    ap.add_argument("--budget-s", type=float, help="the whole run's time (default 300 on CUDA, 900 dry)")
    ap.add_argument("--engine-budget-s", type=float, help="the engine section's time (default 150 on CUDA)")
    ap.add_argument("--row-timeout-s", type=float, default=120.0, help="each CLI row's limit")
    ap.add_argument("--jobs", type=int, help="stage chains run at once (default 6 on CUDA, 2 dry)")
    args = ap.parse_args(argv)
    import torch

    cuda = torch.cuda.is_available() and not args.dry
    if not cuda and not args.dry:
        print("gpu_check: no CUDA device; run with --dry for the CPU version of the same checks")
        return 2
    device, dtype = ("cuda", "bfloat16") if cuda else ("cpu", "float32")
    CHILD_ENV.clear()
    CHILD_ENV.update({} if cuda else {"CUDA_VISIBLE_DEVICES": ""})  # --dry on a GPU machine: still the CPU checks
    dtypes = ["bfloat16", "float32"] if cuda else ["float32"]
    batches = [16] if args.quick or not cuda else [16, 64, 256]
    threads = 2 if cuda else 1
    jobs = args.jobs or (6 if cuda else 2)
    budget = args.budget_s or (450.0 if cuda else 900.0)
    engine_budget = args.engine_budget_s or (300.0 if cuda else 120.0)
    stage_ids = list(STAGE_ROWS) if not args.stages else [s.strip() for s in args.stages.split(",") if s.strip()]
    unknown = [s for s in stage_ids if s not in STAGE_ROWS]
    if unknown:
        ap.error(f"--stages: unknown {unknown}; choose from {', '.join(STAGE_ROWS)}")
    run_engine, run_stages = args.only in (None, "engine"), args.only in (None, "stages")

    t_all = time.time()
    deadline = t_all + budget
    env = versions(cuda)
    print(f"gpu_check on {env['device']}: torch {env['torch']} (CUDA {env['cuda']}), transformers "
          f"{env['transformers']}, accelerate {env['accelerate']}, peft {env['peft']}, python {env['python']}",
          flush=True)
    names = [engine_row_name(*c) for c in engine_plan(dtypes, batches, cuda)] if run_engine else []
    names += [stage_row_name(s, dtype) for s in stage_ids] if run_stages else []
    report = Report(names, env, args.json)
    runner = Runner()

    def on_term(signum, frame):
        raise Stop()

    old = signal.signal(signal.SIGTERM, on_term) if threading.current_thread() is threading.main_thread() else None
    try:
        with tempfile.TemporaryDirectory(prefix="posttrain-gpu-check-") as tmp:
            tmp = Path(tmp)
            model_dir = args.model or build_model(tmp / "model", args.dry)
            # stages first (the correctness checks; each row has its own timeout), then the engine section with
            # the time left (the static-cache cells, which compile, go last within it)
            if run_stages:
                stage_section(runner, report, stage_ids, model_dir, tmp / "stages", dtype, threads, jobs,
                              deadline - (40 if run_engine else 0), args.row_timeout_s, cuda)
            if run_engine:  # killed 60 s past its budget, so the budget leaves those 60 s and some to spare
                engine_section(runner, report, model_dir, device, dtypes, batches, tmp,
                               min(engine_budget, deadline - time.time() - 75), threads if not cuda else 0)
    except (Stop, KeyboardInterrupt):
        print("[gpu_check] stopped (signal): the rows not run yet say so", flush=True)
    except Exception as e:  # e.g. building the model failed: the rows say "not run", the table still prints
        report.env["error"] = f"{type(e).__name__}: {e}"[:300]
        print(f"[gpu_check] error: {report.env['error']}", flush=True)
    finally:
        runner.kill_all()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
        report.env["seconds"] = round(time.time() - t_all, 1)
        report.save()
    print(f"\ngpu_check on {env['device']} (torch {env['torch']}, transformers {env['transformers']}, accelerate "
          f"{env['accelerate']}, peft {env['peft']}; {report.env['seconds']} s)")
    print(report.table(), flush=True)
    return 0 if report.ok() else 1


def engine_section(runner: Runner, report: Report, model_dir: Path, device: str, dtypes: list[str],
                   batches: list[int], tmp: Path, budget_s: float, threads: int) -> None:
    """The engine rows in a child process (`--engine-worker`), killed 60 s after its budget if it hangs."""
    out = tmp / "engine-rows.json"
    spec = tmp / "engine-spec.json"
    spec.write_text(json.dumps({"model_dir": str(model_dir), "device": device, "dtypes": dtypes, "batches": batches,
                                "budget_s": budget_s, "out": str(out), "threads": threads}))
    logs = tmp / "logs"
    logs.mkdir(exist_ok=True)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TOKENIZERS_PARALLELISM": "false", **CHILD_ENV}
    rc, last = runner.run([sys.executable, str(SCRIPT), "--engine-worker", str(spec)], ROOT, env,
                          max(budget_s, 1) + 60, logs / "engine")
    rows = json.loads(out.read_text()) if out.exists() else {}
    for name, row in rows.items():
        report.set(name, row)
    why = ("it ran past its deadline and was killed" if rc is None else f"exit {rc}: {last[:160]}") if rc != 0 \
        else "it ended without reaching this row"
    for kind_dt_b in engine_plan(dtypes, batches, device.startswith("cuda")):
        name = engine_row_name(*kind_dt_b)
        if name not in rows:
            report.set(name, {"status": f"FAILED: the engine section stopped first ({why})"})


def stage_section(runner: Runner, report: Report, stage_ids: list[str], model_dir: Path, root: Path, dtype: str,
                  threads: int, jobs: int, deadline: float, row_timeout: float, cuda: bool) -> None:
    """Every chain of stage rows; chains concurrently (`jobs`), the rows of one chain in order."""
    chains: dict[str, list[str]] = {}
    for sid in stage_ids:
        chains.setdefault(STAGE_ROWS[sid][3], []).append(sid)

    def run_chain(chain: str, sids: list[str]) -> None:
        out = root / chain
        for sid in sids:
            name = stage_row_name(sid, dtype)
            if sid == "fsdp" and not cuda:
                report.set(name, {"status": "skipped: needs CUDA"})
                continue
            launch = [sys.executable]
            if sid == "fsdp":
                launch += ["-m", "accelerate.commands.launch", "--config_file",
                           str(ROOT / "recipes" / "launch" / "fsdp.yaml"), "--num_processes", "1"]
            cmd = stage_command(sid, model_dir, out, dtype, threads, launch)
            try:
                row = stage_row(runner, sid, cmd, out, min(row_timeout, deadline - time.time()))
            except Stop:
                return
            except Exception as e:  # our bug, not the stage's: still one row
                row = {"status": f"FAILED: gpu_check: {type(e).__name__}: {e}"[:200]}
            report.set(name, row)

    order = sorted(chains.items(), key=lambda kv: -len(kv[1]))  # the longest chain first
    pool = ThreadPoolExecutor(max_workers=max(1, jobs))
    try:
        for f in [pool.submit(run_chain, c, s) for c, s in order]:
            f.result()
    except BaseException:  # Stop: kill the running rows, so the threads end now
        runner.kill_all()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


if __name__ == "__main__":
    raise SystemExit(main())
