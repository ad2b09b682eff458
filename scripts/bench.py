"""Benchmarks, measured side by side in one run and reported as ratios (never timed assertions in tests).

Sections (`--only NAME`, repeatable; later issues add trainer sections to SECTIONS):
  generate  the rollout engine (`posttrain.rollout.generate`) against `model.generate` on the same
            random-init preset, prompts (16-48 tokens, mixed), settings (sampling at temperature 1, no
            top-k / top-p) and seed; both produce exactly max_new_tokens per row (`min_new_tokens` for
            generate, `ignore_eos=True` for the engine). Warm-up excluded, runs alternate, medians.
  dpo       our DPO training loop (trainers/dpo.py's pair_logps / pair_loss / reference_logps with
            loop.optimizer_step) against TRL's DPOTrainer (optional: `pip install -e '.[bench]'`) on
            the same tiny model, tiny-summarize pairs, batch (8), lr and beta, TRL set up for this CPU
            (fp32, no gradient checkpointing); tokens/s of the same pairs, reference log-probs included.
  grpo      a GRPO step of `posttrain grpo` (the trainer, through the CLI) against TRL's GRPOTrainer on the
            same random-init tiny model, prompts, 2 prompts x 8 completions x <= 64 tokens, reward (length
            verifier), beta 0, one pass, TRL set up for this CPU (fp32, no gradient checkpointing); s/step.

CPU:       python scripts/bench.py --quick            (< 2 min on 2 cores)
           python scripts/bench.py --only generate --threads 2 --json runs/bench.json
Multi-GPU: not applicable (single-process microbenchmarks; `--device cuda` runs the generate section on one GPU).
Runtime:   --quick about 1 min on 2 CPU cores when the machine is otherwise idle; full about 4 min.

Achieved GFLOP/s counts the same useful work for both implementations:
  FLOPs = 2*N_block*(sum_prompt_tokens + B*(M-1)) + 2*N_head*B*M + 4*L*H*Dh*(attended key positions)
with N_block the parameters of the transformer blocks, N_head = d_model*V (the logits matmul, run once
per sampled token), M new tokens per row, and attended positions summed over every fed token (a prompt
token at position i attends to i+1 keys, the t-th new token to prompt_len+t). The reference is the
machine's fp32 matmul rate, measured first with a large torch.matmul on the same threads.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import random
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from posttrain.models import PRESETS, build_model, count_parameters, train_tokenizer  # noqa: E402
from posttrain.rollout import generate, select_backend  # noqa: E402


# ------------------------------------------------------------------ shared helpers


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())



def matmul_gflops(n: int, repeats: int, device: str = "cpu") -> float:
    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)
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


# ------------------------------------------------------------------ section: generate


def bench_generate(args) -> dict:
    device = args.device
    presets = args.presets
    batches = args.batches
    M = args.max_new_tokens
    repeats = args.repeats
    peak = matmul_gflops(1024 if args.quick else 2048, 5 if args.quick else 10, device)
    print(f"fp32 matmul rate ({'1024' if args.quick else '2048'}^3, {torch.get_num_threads()} threads): "
          f"{peak:.0f} GFLOP/s")
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
    return dict(matmul_gflops=peak, rows=rows_out)


# ------------------------------------------------------------------ section: dpo


def _summarize_pairs(n: int, seed: int = 0) -> list[dict]:
    """n preference rows from the tiny-summarize generator: chosen = the reference summary, rejected =
    another document's summary (realistic lengths; the labels do not matter for throughput)."""
    from posttrain.tasks import get_task

    ex = get_task("tiny-summarize").make_examples(n + 1, seed, "train")
    return [{"prompt": ex[i]["prompt"], "chosen": ex[i]["completion"], "rejected": ex[i + 1]["completion"],
             "_row": i + 1} for i in range(n)]


def bench_dpo(args) -> dict:
    """Our DPO training loop against TRL's DPOTrainer on the same tiny model, pairs, batch and lr.

    Both train one pass over the same S*B pairs (S steps of B pairs), so they process exactly the same
    tokens; tokens/s = (prompt+chosen + prompt+rejected tokens of those pairs) / wall time. Ours is timed
    from the reference precompute (the SFT model's log-probs of every pair, done once) to the last
    optimizer step; TRL's from `trainer.train()` to its return (its reference model runs every step,
    its default); with precompute_ref_log_probs=True (second row) TRL computes them in its constructor, so
    a second, identical precompute pass is timed alone and added to its train() time. TRL is configured for this CPU: fp32 (bf16=False), gradient_checkpointing=False,
    no logging / saving / eval. Each side runs once untimed first (warm-up); runs alternate; medians.
    """
    import copy
    import tempfile

    from posttrain import loop
    from posttrain.preferences import check_pairs, collate_pairs
    from posttrain.tasks import tokenizer_corpus
    from posttrain.config import TaskConfig
    from posttrain.trainers.dpo import DPOConfig, pair_logps, pair_loss, reference_logps

    B = args.dpo_batch
    S = 6 if args.quick else 16
    repeats = 3 if args.quick else 5
    max_len = 256
    tok = train_tokenizer(tokenizer_corpus(TaskConfig(name="tiny-summarize", n_train=2000)), vocab_size=1024)
    rows = _summarize_pairs(S * B)
    _, pairs, _ = check_pairs(rows, "bench pairs", "error", tok, max_len)
    tokens = sum(2 * len(p.prompt) + len(p.chosen) + len(p.rejected) for p in pairs)
    base = build_model("tiny", tok, seed=0).to(args.device)
    print(f"tiny: {count_parameters(base) / 1e6:.2f}M parameters; {S} steps x {B} pairs, "
          f"{tokens / len(pairs):.0f} tokens per pair (prompt twice + chosen + rejected), lr 1e-4, beta 0.1")
    cfg = DPOConfig(batch_size=B, lr=1e-4, beta=0.1)
    pad = tok.pad_token_id

    def ours() -> float:
        model = copy.deepcopy(base)
        accelerator = loop.setup(0)
        t0 = time.perf_counter()
        ref = reference_logps(model, pairs, pad, B)
        optimizer = loop.build_optimizer(model, cfg.lr)
        scheduler = loop.build_scheduler(optimizer, 0, S, "constant")
        for step in range(S):
            idx = list(range(step * B, (step + 1) * B))
            batch = collate_pairs([pairs[i] for i in idx], pad, share_prompt=True)
            r = {k: v[idx] for k, v in ref.items()}

            def loss_fn(mb):
                s, n = pair_logps(model, mb)
                return pair_loss(cfg, s, n, r)

            loop.optimizer_step(accelerator, model, optimizer, scheduler, [batch], loss_fn, 1.0, step + 1)
        _sync(args.device)
        return time.perf_counter() - t0

    try:
        import trl  # noqa: F401
        from datasets import Dataset
        from transformers import logging as hf_logging
        from trl import DPOConfig as TRLConfig, DPOTrainer
    except ImportError as e:
        print(f"TRL not installed ({e}); `pip install -e '.[bench]'` to compare. Ours alone:")
        t = statistics.median(ours() for _ in range(repeats + 1))
        print(f"ours: {tokens / t:.0f} tokens/s")
        return dict(ours_tok_s=tokens / t)
    hf_logging.set_verbosity_error()
    import datasets
    from transformers.trainer_callback import PrinterCallback

    datasets.disable_progress_bars()
    data = [{k: r[k] for k in ("prompt", "chosen", "rejected")} for r in rows]
    tmp = tempfile.mkdtemp(prefix="posttrain-bench-trl-")

    def trl_run(precompute: bool = False) -> float:
        targs = TRLConfig(precompute_ref_log_probs=precompute, precompute_ref_batch_size=B, output_dir=tmp, per_device_train_batch_size=B, num_train_epochs=1, learning_rate=1e-4,
                          lr_scheduler_type="constant", beta=0.1, max_length=max_len, bf16=False, fp16=False,
                          gradient_checkpointing=False, use_cpu=args.device == "cpu", logging_strategy="no",
                          save_strategy="no", eval_strategy="no", report_to=[], disable_tqdm=True,
                          dataloader_num_workers=0, seed=0)
        ref = None if precompute else copy.deepcopy(base).eval()
        train_data = Dataset.from_list(data)
        train_data._fingerprint = f"posttrain-bench-{time.time_ns()}"  # no reuse of TRL's cached reference log-probs
        model = copy.deepcopy(base)
        with contextlib.redirect_stderr(io.StringIO()):  # TRL's own progress bars
            trainer = DPOTrainer(model=model, ref_model=ref, args=targs, train_dataset=train_data,
                                 processing_class=tok)
            trainer.remove_callback(PrinterCallback)
            t_pre = 0.0
            if precompute:  # TRL ran it in the constructor (with dataset bookkeeping): time one more pass alone
                ds = trainer.train_dataset.remove_columns(["ref_chosen_logps", "ref_rejected_logps"])
                ds._fingerprint = f"posttrain-bench-{time.time_ns()}"
                t0 = time.perf_counter()
                trainer._precompute_ref_logps(ds, "train", B)
                t_pre = time.perf_counter() - t0
            t0 = time.perf_counter() - t_pre
            out = trainer.train()
        _sync(args.device)
        dt = time.perf_counter() - t0
        assert out.global_step == S, f"TRL ran {out.global_step} steps, expected {S}"
        return dt

    ours(), trl_run(), trl_run(True)  # warm-up
    t_ours, t_trl, t_trl_pre = [], [], []
    for _ in range(repeats):
        t_trl.append(trl_run())
        t_ours.append(ours())
        t_trl_pre.append(trl_run(True))
    mo, mt, mp = statistics.median(t_ours), statistics.median(t_trl), statistics.median(t_trl_pre)
    row = dict(batch=B, steps=S, tokens=tokens, ours_tok_s=tokens / mo, trl_tok_s=tokens / mt,
               trl_precompute_tok_s=tokens / mp, ratio=mt / mo, ratio_vs_trl_precompute=mp / mo,
               ours_times=t_ours, trl_times=t_trl, trl_precompute_times=t_trl_pre)
    print(f"{'implementation':<44} {'tokens/s':>9} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL DPOTrainer, live reference (its default)':<44} {tokens / mt:>9.0f} {mt / S:>7.3f} "
          f"{mt / mo:>6.2f}x")
    print(f"{'TRL DPOTrainer, precompute_ref_log_probs':<44} {tokens / mp:>9.0f} {mp / S:>7.3f} {mp / mo:>6.2f}x")
    print(f"{'posttrain DPO loop (reference precomputed)':<44} {tokens / mo:>9.0f} {mo / S:>7.3f} {'1.00x':>7}")
    print("ratio = TRL time / posttrain time for the same pairs (both include their reference log-probs).")
    return row


# ------------------------------------------------------------------ section: grpo


def bench_grpo(args) -> dict:
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
    """
    import contextlib
    import io
    import shutil
    import tempfile

    from posttrain.cli import main as posttrain_main
    from posttrain.models import save_model
    from verifiers.format import LengthVerifier

    steps = 8 if args.quick else 14
    rounds = 1 if args.quick else 2
    root = Path(tempfile.mkdtemp(prefix="posttrain-bench-grpo-"))
    corpus = _corpus(300)
    tok = train_tokenizer(corpus, vocab_size=1024)
    base = build_model("tiny", tok, seed=0)
    save_model(base, tok, root / "model")
    prompts = [" ".join(c.split()[:20]) for c in corpus[:64]]
    (root / "problems.jsonl").write_text("".join(json.dumps({"prompt": p, "answer": "-", "verifier": "length"}) + "\n"
                                                for p in prompts))
    recipe = root / "bench-grpo.yaml"
    recipe.write_text(f"""# GRPO step benchmark (scripts/bench.py); posttrain grpo --recipe this file, ~1 min
task: {{name: tiny-countdown, n_train: 16, n_eval: 8}}
model: {{path: {root / 'model'}, max_length: 256}}
grpo:
  verifier: length
  verifier_options: {{max_chars: 150}}
  verifier_workers: 0
  train_file: {root / 'problems.jsonl'}
  prompts_per_step: 2
  group_size: 8
  max_new_tokens: {args.max_new_tokens}
  zero_variance: keep
  lr: 1.0e-4
  eval_every: 0
  eval_rows: 0
  final_eval_rows: 0
  save_every: 0
""")
    sft = root / "runs" / "bench-grpo" / "sft" / "final"
    sft.parent.mkdir(parents=True)
    shutil.copytree(root / "model", sft)
    print(f"tiny: {count_parameters(base) / 1e6:.2f}M parameters; 2 prompts x 8 completions x <= {args.max_new_tokens} "
          f"tokens per step, {steps} steps per run ({rounds} run(s) each, first 2 steps excluded)")

    def ours() -> tuple[list[float], dict[str, float]]:
        with contextlib.redirect_stdout(io.StringIO()):
            rc = posttrain_main(["grpo", "--recipe", str(recipe), f"run.output_dir={root / 'runs'}",
                                 f"run.threads={args.threads}", "run.quiet=true", f"max_steps={steps}"])
        assert rc == 0, "posttrain grpo failed"
        rows = [json.loads(l) for l in (root / "runs" / "bench-grpo" / "grpo" / "metrics.jsonl").read_text().splitlines()]
        rows = [r for r in rows if "time/step" in r][2:]
        phases = {k: statistics.median(r[f"time/{k}"] for r in rows) for k in ("sample", "score", "train")}
        phases["completion_tokens"] = statistics.mean(r["completion/length"] for r in rows)
        return [r["time/step"] for r in rows], phases

    try:
        from datasets import Dataset
        from transformers import TrainerCallback
        from transformers import logging as hf_logging
        from transformers.trainer_callback import PrinterCallback
        from trl import GRPOConfig as TRLConfig, GRPOTrainer
    except ImportError as e:
        print(f"TRL not installed ({e}); `pip install -e '.[bench]'` to compare. Ours alone:")
        t, phases = ours()
        print(f"ours: {statistics.median(t):.3f} s/step ({phases})")
        return dict(ours_s_per_step=statistics.median(t), ours_phases=phases)
    hf_logging.set_verbosity_error()
    import datasets

    datasets.disable_progress_bars()
    length = LengthVerifier(max_chars=150)

    def length_reward(completions, **kwargs):
        return [length.check(c, None).score for c in completions]

    class StepTimer(TrainerCallback):
        def __init__(self):
            self.times, self.t0, self.tokens = [], 0.0, []

        def on_step_begin(self, *a, **k):
            self.t0 = time.perf_counter()

        def on_step_end(self, *a, **k):
            _sync(args.device)
            self.times.append(time.perf_counter() - self.t0)

    def trl_run() -> list[float]:
        import copy

        targs = TRLConfig(output_dir=str(root / "trl"), per_device_train_batch_size=16, num_generations=8,
                          max_completion_length=args.max_new_tokens, temperature=1.0, beta=0.0, num_iterations=1,
                          learning_rate=1e-4, lr_scheduler_type="constant", max_grad_norm=1.0, max_steps=steps,
                          bf16=False, fp16=False, gradient_checkpointing=False, use_cpu=args.device == "cpu",
                          logging_strategy="no", save_strategy="no", report_to=[], disable_tqdm=True,
                          dataloader_num_workers=0, seed=0)
        timer = StepTimer()
        with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
            trainer = GRPOTrainer(model=copy.deepcopy(base), reward_funcs=[length_reward], args=targs,
                                  train_dataset=Dataset.from_list([{"prompt": p} for p in prompts]),
                                  processing_class=tok, callbacks=[timer])
            trainer.remove_callback(PrinterCallback)
            out = trainer.train()
        assert out.global_step == steps, f"TRL ran {out.global_step} steps, expected {steps}"
        return timer.times[2:]

    t_ours, t_trl, phases = [], [], {}
    for _ in range(rounds):  # alternate, so drifting load hits both
        t, phases = ours()
        t_ours += t
        t_trl += trl_run()
    mo, mt = statistics.median(t_ours), statistics.median(t_trl)
    print(f"{'implementation':<58} {'s/step':>7} {'ratio':>7}")
    print(f"{'TRL GRPOTrainer (fp32, no gradient checkpointing)':<58} {mt:>7.3f} {mt / mo:>6.2f}x")
    print(f"{'posttrain grpo':<58} {mo:>7.3f} {'1.00x':>7}")
    print(f"posttrain phases (medians): sample {phases['sample']:.3f} s, score {phases['score']:.3f} s, "
          f"update {phases['train']:.3f} s; {phases['completion_tokens']:.1f} completion tokens per row")
    print("ratio = TRL time per step / posttrain time per step, same model, prompts, group size and budget.")
    shutil.rmtree(root, ignore_errors=True)
    return dict(steps_per_run=steps, rounds=rounds, ours_s_per_step=mo, trl_s_per_step=mt, ratio=mt / mo,
                ours_phases=phases, ours_times=t_ours, trl_times=t_trl)


SECTIONS = {
    "generate": bench_generate,
    "dpo": bench_dpo,
    "grpo": bench_grpo,
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and a smaller matmul probe (< 2 min)")
    ap.add_argument("--only", action="append", choices=sorted(SECTIONS), help="run only these sections")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--presets", default="tiny,small", help="comma-separated model presets")
    ap.add_argument("--batches", default="1,16,64", help="comma-separated batch sizes")
    ap.add_argument("--max-new-tokens", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per implementation (default 5 quick, 9)")
    ap.add_argument("--dpo-batch", type=int, default=8, help="pairs per step in the dpo section (default 8)")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args(argv)
    args.presets = [p for p in args.presets.split(",") if p]
    unknown = [p for p in args.presets if p not in PRESETS]
    if unknown:
        ap.error(f"unknown preset(s) {unknown}; choose from {sorted(PRESETS)}")
    args.batches = [int(b) for b in args.batches.split(",") if b]
    args.repeats = args.repeats or (5 if args.quick else 9)
    torch.set_num_threads(args.threads)
    print(f"posttrain bench: torch {torch.__version__}, {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} threads, device {args.device}, {'quick' if args.quick else 'full'}; "
          f"load average {_load()}")
    t0 = time.perf_counter()
    results = {}
    for name in args.only or list(SECTIONS):
        print(f"\n== {name} ==")
        results[name] = SECTIONS[name](args)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s; load average {_load()}")
    if os.getloadavg()[0] > 1.5:
        print("note: other processes were using the CPU; with shared cores, OpenMP threads stall at barriers "
              "and timings (both columns) swing widely. Rerun on an idle machine for stable ratios.")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(dict(threads=args.threads, device=args.device, quick=args.quick,
                                             torch=torch.__version__, sections=results), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
