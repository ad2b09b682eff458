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
`token_share` for PPO's token means).
"""
from __future__ import annotations

from contextlib import nullcontext
from typing import Any

import torch

from posttrain.data import row_spans, token_groups
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


def sharded_logprobs(accelerator, model, batch: Any, micro_batch_size: int, temperature: float = 1.0,
                     max_tokens: int = 0) -> torch.Tensor:
    """No-grad log-probs (B, T) of every row of `batch` (input_ids / attention_mask / completion_mask) under
    `model`: each process computes its rows r, r + W, ... (micro-batches of at most `micro_batch_size` rows and
    `max_tokens` padded tokens), then they are gathered, so every process holds all rows (shares padded to
    the largest one for the gather). In the run's precision (`run_precision`): a frozen reference that accelerate
    never prepared runs under the same bf16 autocast as the policy, as TRL's does."""
    with run_precision(accelerator):
        return _sharded_logprobs(accelerator, model, batch, micro_batch_size, temperature, max_tokens)


def run_precision(accelerator):
    """The run's mixed-precision context (accelerate's autocast: bf16 under run.mixed_precision=bf16, else off) for
    forwards of models accelerate never prepared (frozen references, teachers); a no-op without an accelerator."""
    autocast = getattr(accelerator, "autocast", None)
    return autocast() if autocast is not None else nullcontext()


def _sharded_logprobs(accelerator, model, batch: Any, micro_batch_size: int, temperature: float,
                      max_tokens: int) -> torch.Tensor:
    if accelerator is None or accelerator.num_processes == 1:
        return batched_logprobs(model, batch, micro_batch_size, temperature=temperature, max_tokens=max_tokens)[0]
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
        local[:len(own)] = batched_logprobs(model, rows, micro_batch_size, temperature=temperature,
                                            max_tokens=max_tokens)[0]
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
                  rank: int = 0, world: int = 1, max_tokens: int = 0,
                  by_length: bool = True) -> list[tuple[dict[str, torch.Tensor], float, float]]:
    """This process's micro-batches of the minibatch `idx` (process r takes rows r, r + W, ... of it), all-padding
    columns trimmed, each with (its share of the minibatch loss, its share of the minibatch's loss tokens).

    Shares are fractions of the WHOLE minibatch (all processes): aggregation "token_mean" weighs by loss
    tokens (`rows["loss_mask"]`), the others by rows, so the shares of all micro-batches of all processes sum
    to 1 and the accumulated (and, under DDP, averaged x W) gradient is the whole minibatch's aggregation.
    A micro-batch has at most `micro` rows (0: no row limit) and `max_tokens` padded tokens (0: no limit), rows
    of like length together unless `by_length=False` (`data.token_groups`).
    A process without rows gets one copy of a real row with share 0; `loop.optimizer_step` evens out the
    numbers of micro-batches across processes, so the DDP all-reduces line up."""
    total_rows = len(idx)
    total_tokens = float(rows["loss_mask"][idx].sum())
    mine = idx[rank::world]
    groups = token_groups(row_spans(rows["attention_mask"][mine]), micro, max_tokens, by_length=by_length) \
        if len(mine) else [[]]
    out = []
    for g in groups:
        sel = mine[torch.as_tensor(g, dtype=torch.long, device=mine.device)]
        real = len(sel) > 0
        if not real:
            sel = idx[:1]
        mb = trim_columns({k: v[sel] for k, v in rows.items()})
        tokens = float(mb["loss_mask"].sum()) / total_tokens if real else 0.0
        share = tokens if aggregation == "token_mean" else (len(sel) / total_rows if real else 0.0)
        out.append((mb, share, tokens))
    return out


def token_share(accelerator, loss: torch.Tensor, n_local: float, n_global: float) -> torch.Tensor:
    """A token-mean loss over `n_local` of a minibatch's `n_global` loss tokens (all processes), times
    n_local / n_global * W: summed over a process's micro-batches and averaged over the W processes by DDP, the
    gradient is the whole minibatch's token mean, as one process computes it in one piece. Pass n_local /
    n_global as the micro-batch's weight to `loop.optimizer_step` and its token-mean metrics are the
    minibatch's too (PPO)."""
    W = 1 if accelerator is None else accelerator.num_processes
    return loss * (n_local * W / n_global)


def global_explained_variance(accelerator, values: torch.Tensor, returns: torch.Tensor,
                              completion_mask: torch.Tensor) -> float:
    """`losses.value_loss`'s explained variance, 1 - Var(R - V) / Var(R), over the completion tokens of
    every process's rows (from summed first and second moments)."""
    cm = completion_mask.bool()
    r = returns.detach()[cm].double()
    d = (returns.detach() - values.detach())[cm].double()
    count = torch.tensor(float(r.numel()), dtype=torch.float64, device=r.device)
    t = torch.stack([count, r.sum(), (r * r).sum(), d.sum(), (d * d).sum()]).to(accelerator.device)
    n, sr, srr, sd, sdd = accelerator.reduce(t, reduction="sum").tolist()
    var_r, var_d = srr - sr * sr / max(n, 1.0), sdd - sd * sd / max(n, 1.0)  # both times (n - 1)
    return 1.0 - var_d / var_r if var_r > 0 else float("nan")
