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


SECTIONS = {
    "generate": bench_generate,
    "dpo": bench_dpo,
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
