"""Write the conversational example datasets in data/chat/ from the seeded tiny-summarize generator.

CPU:        python scripts/make_chat_data.py            (a second; rewrites data/chat/*.jsonl byte for byte)
Multi-GPU:  not applicable (no model involved).

What it writes (TRL's conversational formats; schemas in data/README.md):
- `summarize-sft-train.jsonl` (600 rows) and `summarize-sft-eval.jsonl` (100 rows): `messages` conversations,
  a system message and two user/assistant exchanges each (summarise a document, then another). Every
  assistant turn is trained on; `meta` is the task's meta of the last document, so the held-out gold metrics
  of tiny-summarize score the last reply.
- `summarize-prefs.jsonl` (600 rows): the implicit-prompt preference form, `chosen` and `rejected` whole
  conversations sharing their first turns: the chosen reply is the document's concise summary (in the length
  band, every fact), the rejected one is the summary of another document (wrong names and facts).

Deterministic: the rows depend only on the generator's (n, seed, split) and the fixed seeds below.

    posttrain sft --recipe tiny-summarize task.train_file=data/chat/summarize-sft-train.jsonl \
        task.eval_file=data/chat/summarize-sft-eval.jsonl
    posttrain dpo --recipe tiny-summarize task.train_file=data/chat/summarize-sft-train.jsonl \
        task.eval_file=data/chat/summarize-sft-eval.jsonl dpo.train_file=data/chat/summarize-prefs.jsonl
"""
from __future__ import annotations

import argparse
import json
import random
from pathlib import Path

from posttrain.tasks import summarize

SYSTEM = "You write one-sentence summaries of short documents."


def _exchange(example: dict) -> list[dict]:
    return [{"role": "user", "content": example["prompt"]},
            {"role": "assistant", "content": example["completion"].strip()}]


def sft_rows(n: int, split: str, seed: int) -> list[dict]:
    """`n` two-exchange conversations from 2n generated examples of `split`."""
    examples = summarize.make_examples(2 * n, seed, split)
    return [{"messages": [{"role": "system", "content": SYSTEM}, *_exchange(a), *_exchange(b)], "meta": b["meta"]}
            for a, b in zip(examples[0::2], examples[1::2])]


def preference_rows(n: int, seed: int) -> list[dict]:
    """`n` implicit-prompt pairs: the concise summary against another document's summary."""
    examples = summarize.make_examples(n, seed, "train")
    rng = random.Random(f"chat-prefs:{seed}")
    rows = []
    for i, ex in enumerate(examples):
        other = examples[(i + rng.randrange(1, n)) % n]
        prompt = [{"role": "user", "content": ex["prompt"]}]
        rows.append({"chosen": prompt + [{"role": "assistant", "content": ex["meta"]["concise_summary"]}],
                     "rejected": prompt + [{"role": "assistant", "content": other["meta"]["concise_summary"]}],
                     "meta": ex["meta"]})
    return rows


def write(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r, ensure_ascii=False) + "\n" for r in rows), encoding="utf-8")
    print(f"wrote {len(rows)} rows to {path}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "data" / "chat"))
    args = parser.parse_args(argv)
    out = Path(args.out)
    write(out / "summarize-sft-train.jsonl", sft_rows(600, "train", seed=0))
    write(out / "summarize-sft-eval.jsonl", sft_rows(100, "eval", seed=0))
    write(out / "summarize-prefs.jsonl", preference_rows(600, seed=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
