"""Several processes (`accelerate launch`, data parallel): strided sharding, gathering, token-mean rescaling.

CPU: `python -c "import posttrain.sharding"`; multi-process behaviour is tested against one process in
tests/posttrain/test_distributed.py (2 CPU processes over gloo). With one process every function here is
the identity (or one plain call), so the trainers read the same in both cases.

The one convention: process r of W holds the rows at global positions r, r + W, ... (`positions`) of a
batch that every process agrees on (the trainers draw it from `loop.batch_indices`, a pure function of
seed and step). What a process computes on its rows (samples, scores, no-grad log-probs) is gathered back
into global order, so everything computed from the gathered batch (normalisation, advantages, whitening,
dynamic sampling, logged statistics) is global and identical on every process. Updates split each global
minibatch the same strided way; each process scales its loss to its share of the whole minibatch times W,
so DDP's gradient average is the one-process gradient (`micro_batches` for GRPO's aggregations,
`global_token_mean` for PPO's token means).
"""
from __future__ import annotations

from typing import Any

import torch

from posttrain.logprobs import batched_logprobs


def positions(n: int, rank: int, world: int) -> list[int]:
    """This process's positions in a global batch of n rows: rank, rank + world, ..."""
    return list(range(rank, n, world))


def gather_rows(accelerator, items: list, where: list[int]) -> list:
    """Every process's `items` (picklable; item i sits at global position where[i]), in global order."""
    if accelerator is None or accelerator.num_processes == 1:
        return list(items)
    from accelerate.utils import gather_object

    pairs = gather_object(list(zip(where, items)))
    return [x for _, x in sorted(pairs, key=lambda t: t[0])]


def gather_row_tensor(accelerator, local: torch.Tensor, where: list[int]) -> torch.Tensor:
    """Every process's rows (n, ...) (the same n and trailing shape everywhere) -> (W * n, ...) in global order."""
    if accelerator is None or accelerator.num_processes == 1:
        return local
    rows = accelerator.gather(local.contiguous())  # (W * n, ...) process-major
    at = accelerator.gather(torch.as_tensor(where, dtype=torch.long, device=local.device))  # (W * n,)
    return torch.empty_like(rows).index_copy_(0, at, rows)


def sharded_logprobs(accelerator, model, batch: Any, micro_batch_size: int, temperature: float = 1.0) -> torch.Tensor:
    """No-grad log-probs (B, T) of every row of `batch` (input_ids / attention_mask / completion_mask) under
    `model`: each process computes its rows r, r + W, ..., then they are gathered, so every process holds
    all rows (shares padded to the largest one for the gather)."""
    if accelerator is None or accelerator.num_processes == 1:
        return batched_logprobs(model, batch, micro_batch_size, temperature=temperature)[0]
    rank, world = accelerator.process_index, accelerator.num_processes
    ids = batch["input_ids"] if isinstance(batch, dict) else batch.input_ids
    am = batch["attention_mask"] if isinstance(batch, dict) else batch.attention_mask
    cm = batch["completion_mask"] if isinstance(batch, dict) else batch.completion_mask
    B, T = ids.shape
    own = torch.arange(rank, B, world, device=ids.device)
    share = -(-B // world)  # rows of the largest share
    local = torch.zeros(share, T, dtype=torch.float32, device=ids.device)
    if len(own):
        rows = {"input_ids": ids[own], "attention_mask": am[own], "completion_mask": cm[own]}
        local[:len(own)] = batched_logprobs(model, rows, micro_batch_size, temperature=temperature)[0]
    every = accelerator.gather(local)  # (W * share, T), process-major
    out = torch.empty(B, T, dtype=torch.float32, device=every.device)
    for p in range(world):
        n = len(range(p, B, world))
        out[p::world] = every[p * share:p * share + n]
    return out


def trim_columns(rows: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Drop the columns that are padding in every row (every (b, T) tensor sliced alike; others kept)."""
    live = rows["attention_mask"].any(0).nonzero()
    lo, hi = int(live[0]), int(live[-1]) + 1
    return {k: (v[:, lo:hi] if v.dim() == 2 else v) for k, v in rows.items()}


def micro_batches(rows: dict[str, torch.Tensor], idx: torch.Tensor, micro: int, aggregation: str,
                  rank: int = 0, world: int = 1) -> list[tuple[dict[str, torch.Tensor], float, float]]:
    """This process's micro-batches of the minibatch `idx` (process r takes rows r, r + W, ... of it), all-padding
    columns trimmed, each with (its share of the minibatch loss, its share of the minibatch's loss tokens).

    Shares are fractions of the WHOLE minibatch (all processes): aggregation "token_mean" weighs by loss
    tokens (`rows["loss_mask"]`), the others by rows, so the shares of all micro-batches of all processes sum
    to 1 and the accumulated (and, under DDP, averaged x W) gradient is the whole minibatch's aggregation.
    micro = 0: one micro-batch per process. Every process returns the same number of micro-batches (a process
    short of rows gets copies of a real row with share 0), so the DDP all-reduces of the last one line up."""
    total_rows = len(idx)
    total_tokens = float(rows["loss_mask"][idx].sum())
    mine = idx[rank::world]
    largest = -(-total_rows // world)  # rows of the largest share
    micro = micro or largest
    out = []
    for i in range(-(-largest // micro)):
        sel = mine[i * micro:(i + 1) * micro]
        real = len(sel) > 0
        if not real:
            sel = idx[:1]
        mb = trim_columns({k: v[sel] for k, v in rows.items()})
        tokens = float(mb["loss_mask"].sum()) / total_tokens if real else 0.0
        share = tokens if aggregation == "token_mean" else (len(sel) / total_rows if real else 0.0)
        out.append((mb, share, tokens))
    return out


# Token means among PPO's policy / value metrics: rescaled with the loss by `global_token_mean`.
TOKEN_MEAN_METRICS = frozenset({"clip_frac", "clip_frac_low", "clip_frac_high", "approx_kl", "ratio_mean", "entropy",
                                "value_clip_frac", "value_mean"})


def global_token_mean(accelerator, loss: torch.Tensor, metrics: dict[str, float], n_local: float,
                      n_global: float) -> tuple[torch.Tensor, dict[str, float]]:
    """A process's token-mean loss and metrics over its rows of a minibatch, rescaled by
    n_local / n_global * W: DDP's gradient average and `loop.optimizer_step`'s metric average over
    processes then give the token mean over the whole minibatch, as one process computes it.
    ratio_max becomes the max over processes. A non-finite loss on any process makes every process's
    loss NaN, so all of them stop at the same step (none waits forever in the next all-reduce).
    The identity in one process."""
    W = 1 if accelerator is None else accelerator.num_processes
    if W == 1:
        return loss, metrics
    f = n_local * W / n_global
    out = {k: (v * f if k in TOKEN_MEAN_METRICS else v) for k, v in metrics.items()}
    mine = torch.tensor([[0.0 if bool(torch.isfinite(loss)) else 1.0, metrics.get("ratio_max", 0.0)]],
                        dtype=torch.float64, device=accelerator.device)
    every = accelerator.gather(mine)  # (W, 2)
    if "ratio_max" in metrics:
        out["ratio_max"] = float(every[:, 1].max())
    if float(every[:, 0].sum()) > 0:
        loss = loss * float("nan")
    return loss * f, out


def global_explained_variance(accelerator, values: torch.Tensor, returns: torch.Tensor,
                              completion_mask: torch.Tensor) -> float:
    """`losses.value_loss`'s explained variance, 1 - Var(R - V) / Var(R), over the completion tokens of
    every process's rows (from summed first and second moments)."""
    cm = completion_mask.bool()
    r = returns.detach()[cm].double()
    d = (returns.detach() - values.detach())[cm].double()
    t = torch.stack([torch.tensor(float(r.numel()), dtype=torch.float64), r.sum(), (r * r).sum(), d.sum(),
                     (d * d).sum()]).to(accelerator.device)
    n, sr, srr, sd, sdd = accelerator.reduce(t, reduction="sum").tolist()
    var_r, var_d = srr - sr * sr / max(n, 1.0), sdd - sd * sd / max(n, 1.0)  # both times (n - 1)
    return 1.0 - var_d / var_r if var_r > 0 else float("nan")
