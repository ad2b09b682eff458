"""Forward paths for the rollout engine: the lean Llama-family decoder (`posttrain.lean.decode.LeanLlama`)
over a preallocated KV cache, and the Hugging Face forward (`HFForward`, with its own cache) for everything
else. Both expose the calls the engine's loop uses:
    start(rows, cols, max_pos)           allocate the cache for one micro-batch
    prefill(ids, valid, pos, row_of)     prompts (U, Tp) -> next-token logits for every row (B, V)
    decode(tok, pos, col)                one token per active row (B, 1) -> logits (B, V)
    select(order, col)                   keep / reorder active rows (finished rows dropped)
    release()                            drop the cache
The lean decoder also has a static-shape step (`start(..., static=True)`, `st` input buffers, `step()`: all rows
every step, a replayed CUDA graph on CUDA; see posttrain.lean.decode), which the engine uses on CUDA; the HF
forward has none, so on CUDA it runs the compacting loop (with EOS checked every few steps, see engine).
"""
from __future__ import annotations

import torch

from ..models import accepts, model_device


class HFForward:
    """The model's own forward with its own cache (any causal LM; peft, quantised, other architectures)."""

    name = "hf"

    def __init__(self, model):
        self.model = model
        self.device = model_device(model)
        self.keep_kw = {"logits_to_keep": 1} if accepts(model, "logits_to_keep") else {}
        # transformers 5.2x renamed the KV cache `cache`, in and out; `past_key_values` warns and goes in 5.40
        self.cache_key = "cache" if accepts(model, "cache") else "past_key_values"

    def start(self, rows: int, cols: int, max_pos: int) -> None:
        self.mask = torch.ones(rows, cols, dtype=torch.long, device=self.device)
        self.past = None

    def _call(self, **kw):
        out = self.model(use_cache=True, **kw, **self.keep_kw)
        self.past = out[self.cache_key]
        return out.logits[:, -1]

    def prefill(self, ids, valid, pos, row_of):
        U, Tp = ids.shape
        B = row_of.shape[0]
        self.mask[:B, :Tp] = valid[row_of].long()
        expand = B != U
        if expand and not hasattr(self._cache_probe(), "batch_select_indices"):
            ids, valid, pos, expand = ids[row_of], valid[row_of], pos[row_of], False
        logits = self._call(input_ids=ids, attention_mask=valid.long(), position_ids=pos)  # (U, V)
        if expand:
            self.past.batch_select_indices(row_of)
            logits = logits.index_select(0, row_of)
        return logits

    @staticmethod
    def _cache_probe():
        from transformers import DynamicCache

        return DynamicCache

    def release(self) -> None:
        self.mask = self.past = None

    def decode(self, tok, pos, col: int):
        B = tok.shape[0]
        return self._call(input_ids=tok, attention_mask=self.mask[:B, :col + 1], position_ids=pos[:, None],
                          **{self.cache_key: self.past})

    def select(self, order: list[int], col: int) -> None:
        if order == list(range(len(order))):
            # Only trailing rows dropped: a slice.
            idx = torch.arange(len(order), device=self.device)
        else:
            idx = torch.tensor(order, device=self.device)
        if hasattr(self.past, "batch_select_indices"):
            self.past.batch_select_indices(idx)
        else:  # legacy tuple caches
            self.past = tuple((k[idx], v[idx]) for k, v in self.past)
        self.mask[:len(order)] = self.mask[idx]
