"""The GPU path, checked in one short run: on a CUDA machine (at most ~8 minutes) the rollout engine against
`model.generate` (greedy agreement, tokens/s), one SFT, DPO and GRPO step in bf16 through the CLI, and one SFT
step under accelerate's FSDP2 config (recipes/launch/fsdp.yaml) with one process; one table at the end.

    python scripts/gpu_check.py                    # CUDA: a SmolLM2-135M-shaped model (30 layers, d=576, GQA 9/3)
    python scripts/gpu_check.py --model DIR        # a real model directory instead (e.g. `posttrain models fetch`)
    python scripts/gpu_check.py --dry              # CPU: the same code on the tiny preset, fp32, FSDP skipped
    python scripts/gpu_check.py --json out.json

Needs only torch, transformers, accelerate and peft beside this project (no vLLM, no DeepSpeed). The GPU
machines reach no network and take 64 MiB of files, so by default the model is SmolLM2-135M-Instruct's
architecture with random weights and a tokenizer trained on the task (the speed and the agreement checks do not
need trained weights; its vocabulary is the task tokenizer's, not 49k). Every row says ok or why not: a failed
row does not stop the others.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SMOL = dict(hidden_size=576, intermediate_size=1536, num_hidden_layers=30, num_attention_heads=9,
            num_key_value_heads=3, max_position_embeddings=2048, tie_word_embeddings=True, rope_theta=100000.0)


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


def engine_vs_generate(model_dir: Path, device: str, dtype) -> dict:
    """Greedy agreement (token for token, one batch of 16 prompts, left-padded) and tokens/s of each."""
    import torch

    from posttrain.chat import encode_prompts
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import generate
    from posttrain.tasks import summarize

    model, tok = load_model(model_dir, dtype, device=device), load_tokenizer(model_dir)
    prompts = [r["prompt"] for r in summarize.make_examples(16, 0, "eval")]
    n = 64
    generate(model, tok, prompts[:2], greedy=True, max_new_tokens=8)  # warm-up (kernels, allocator)
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    sync()
    t0 = time.time()
    ours = generate(model, tok, prompts, greedy=True, max_new_tokens=n)
    sync()
    t_ours = time.time() - t0
    ids = encode_prompts(tok, prompts)
    T = max(map(len, ids))
    x = torch.full((len(ids), T), tok.pad_token_id, dtype=torch.long)
    am = torch.zeros_like(x)
    for i, p in enumerate(ids):
        x[i, T - len(p):], am[i, T - len(p):] = torch.tensor(p), 1
    sync()
    t0 = time.time()
    with torch.no_grad():
        ref = model.generate(x.to(device), attention_mask=am.to(device), max_new_tokens=n, do_sample=False,
                             eos_token_id=tok.eos_token_id, pad_token_id=tok.pad_token_id)[:, T:].tolist()
    sync()
    t_hf = time.time() - t0
    same = 0
    for o, r in zip(ours, ref):
        r = r[:r.index(tok.eos_token_id) + 1] if tok.eos_token_id in r else r
        same += o.completion_ids == r
    tokens = sum(len(o.completion_ids) for o in ours)
    return {"greedy agreement": f"{same}/{len(ours)} rows", "engine tok/s": round(tokens / t_ours),
            "generate tok/s": round(sum(len(r) for r in ref) / t_hf), "ratio": round(t_hf / t_ours, 2)}


def cli_step(stage: str, model_dir: Path, out: Path, dtype: str, threads: int, launch: list[str] | None = None,
             *extra: str) -> dict:
    """One (or two) steps of a stage through the CLI, as a user runs it; seconds and the last logged loss."""
    common = [f"model.path={model_dir}", f"model.dtype={dtype}", f"run.output_dir={out}", "run.quiet=true",
              f"run.threads={threads}", "task.n_train=64", "task.n_eval=8", "model.max_length=256"]
    args = {"sft": ["sft", "--recipe", "tiny-summarize", "max_steps=2", "batch_size=8", "eval_every=0",
                    "final_eval_rows=0", "save_every=0", "warmup_steps=0", "log_every=1"],
            "dpo": ["dpo", "--recipe", "tiny-summarize", "max_steps=2", "batch_size=4", "online=false",
                    "proxy_rm=none", "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0",
                    "log_every=1", "prefs.n_prompts=16", "prefs.n_eval_prompts=4", "prefs.samples_per_prompt=2",
                    "prefs.max_new_tokens=16", "sft.max_steps=1", "sft.final_eval_rows=0", "sft.eval_every=0"],
            "grpo": ["grpo", "--recipe", "tiny-math", "model.start_from=base", "max_steps=2", "prompts_per_step=2",
                     "group_size=4", "max_new_tokens=32", "zero_variance=keep", "eval_every=0", "eval_rows=0",
                     "final_eval_rows=0", "save_every=0"]}[stage]
    cmd = [*(launch or [sys.executable]), "-m", "posttrain", *args, *common, *extra]
    t0 = time.time()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    took = time.time() - t0
    if proc.returncode != 0:
        return {"status": "FAILED: " + (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-1][:160],
                "seconds": round(took, 1)}
    run = out / ("tiny-math" if stage == "grpo" else "tiny-summarize") / stage
    rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
    key = "reward/mean" if stage == "grpo" else "loss"
    last = [r[key] for r in rows if key in r][-1]
    return {"status": "ok", "seconds": round(took, 1), key: round(float(last), 4)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dry", action="store_true", help="CPU: tiny preset, fp32, no FSDP (what a test runs)")
    ap.add_argument("--model", type=Path, help="a model directory instead of the SmolLM2-shaped random model")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    import torch

    cuda = torch.cuda.is_available()
    if not cuda and not args.dry:
        print("gpu_check: no CUDA device; run with --dry for the CPU version of the same checks")
        return 2
    device, dtype = ("cuda", "bfloat16") if cuda and not args.dry else ("cpu", "float32")
    threads = 0 if cuda else 2
    rows: dict[str, dict] = {}
    t_all = time.time()
    with tempfile.TemporaryDirectory(prefix="posttrain-gpu-check-") as tmp:
        tmp = Path(tmp)
        model_dir = args.model or build_model(tmp / "model", args.dry)
        try:
            rows["engine vs generate"] = {"status": "ok", **engine_vs_generate(model_dir, device,
                                                                               getattr(torch, dtype))}
        except Exception as e:  # a row that fails is reported; the others still run
            rows["engine vs generate"] = {"status": f"FAILED: {type(e).__name__}: {e}"[:200]}
        for stage in ("sft", "dpo", "grpo"):
            rows[f"{stage} step ({dtype})"] = cli_step(stage, model_dir, tmp / stage, dtype, threads)
        if cuda and not args.dry:
            launch = [sys.executable, "-m", "accelerate.commands.launch", "--config_file",
                      str(ROOT / "recipes" / "launch" / "fsdp.yaml"), "--num_processes", "1"]
            rows["sft step (FSDP2, 1 process)"] = cli_step("sft", model_dir, tmp / "fsdp", "float32", threads, launch)
        else:
            rows["sft step (FSDP2, 1 process)"] = {"status": "skipped: needs CUDA"}
    env = {"torch": torch.__version__, "device": torch.cuda.get_device_name(0) if cuda else "cpu",
           "seconds": round(time.time() - t_all, 1)}
    print(f"gpu_check on {env['device']} (torch {env['torch']}, {env['seconds']} s)")
    print("| check | status | figures |\n|---|---|---|")
    for name, r in rows.items():
        figures = ", ".join(f"{k} {v}" for k, v in r.items() if k != "status")
        print(f"| {name} | {r['status']} | {figures} |")
    if args.json:
        args.json.write_text(json.dumps({"env": env, "rows": rows}, indent=1))
    return 0 if all(r["status"] == "ok" or r["status"].startswith("skipped") for r in rows.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
