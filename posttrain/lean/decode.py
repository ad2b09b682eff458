"""The rollout engine's lean Llama-family decoder over a preallocated KV cache (`LeanLlama`); the engine
picks it when `posttrain.lean.support.lean_support(model, max_len)` says yes, else the HF forward.

It exposes the calls the engine's loop uses (as `posttrain.rollout.backends.HFForward` does):
    start(rows, cols, max_pos)           allocate the cache for one micro-batch
    prefill(ids, valid, pos, row_of)     prompts (U, Tp) -> next-token logits for every row (B, V)
    decode(tok, pos, col)                one token per active row (B, 1) -> logits (B, V)
    select(order, col)                   keep / reorder active rows (finished rows dropped)
    release()                            drop the cache
and the static-shape step the engine uses on CUDA (`start(..., static=True)`, then `step()`; below).

- Weights are read from the HF module and rearranged once (cached per model by the engine, rewritten
  by `load` when a parameter changes: one strided multiply per matrix): q/k/v fused into one
  ((H+2Hkv)*Dh, d) matrix and gate/up into one (2I, d) matrix, (out, in) as nn.Linear keeps them; each
  RMSNorm weight (times sqrt(d)) and the softmax scale 1/sqrt(Dh) are folded into the matrix that follows,
  so a norm is 3 small ops (x / hypot(|x|, sqrt(d*eps))).
- Packed weights on CPU (`pack_available`, hidden size >= PACK_MIN_HIDDEN): each fused matrix is reordered
  once per `load` into oneDNN's blocked layout and multiplied by its linear kernel (`torch.ops.mkldnn`),
  which skips the repacking a plain matmul does on every call: a higher decode throughput than plain fp32
  matmuls on SmolLM2 at batch 16 (measured: docs/results-archive.md, "Figures once kept in code comments").
  Same numbers within fp32 rounding (tested); `dense(w)` converts one back.
- RoPE: the q/k rows of each head are permuted from the half-split pairing (x_i, x_{i+Dh/2}) that
  `rotate_half` uses to interleaved pairs, so rotating is one complex multiply by a
  (position, Dh/2) table built from the module's own `inv_freq` and `attention_scaling` with the
  same expression as `LlamaRotaryEmbedding` (default, linear, llama3, yarn, ...). q.k is unchanged
  by permuting q and k alike; v is untouched.
- KV cache: k and v tensors (L, B, Hkv, Tmax, Dh) per micro-batch, written in place; rotated k is
  written straight into the cache by the complex multiply (`out=`). All rows share one write column
  (prompts are left-padded); pad keys get an additive -inf mask.
- Decode attention: bmm(q, k^T) + mask -> softmax -> bmm(., v) over (B*Hkv, rep, .) views of the
  cache (GQA without repeating k/v; measured faster than CPU SDPA for one query). It is
  memory-bound: each step reads the whole cache once.
- Prefill: prompts are split into chunks of similar length (dynamic programming over padded tokens
  plus a per-chunk cost), so little compute goes to padding; explicit masked attention; only the last
  position goes through the last layer's MLP and the logits matmul.
- o_proj and down_proj accumulate into the residual stream in place (`addmm_`).
- Finished rows are dropped by moving the last live rows into their slots ("holes"), so a
  compaction copies only as many cache rows as have finished.
- Compressed weights (`weight_dtype=torch.bfloat16`, the rollout's `rollout.dtype`): the fused matrices
  (q/k/v, o, gate/up, down and the head) are stored in bf16 and every matmul runs in bf16 (input rounded
  to bf16, fp32 accumulation inside the kernel, output rounded to bf16, then back to fp32): half the
  weight bytes streamed per decode step and the CPU's native bf16 dot products (AVX512-BF16, AMX) or the
  GPU's. Everything else stays fp32: the residual stream, norms, RoPE, attention and its KV cache, and
  the logits the sampler reads (bf16-rounded: ~3 significant digits). Sampling then follows a slightly
  different distribution from the fp32 policy; the trainers log the gap (`mismatch/kl`).
- Half precision (bf16 / fp16 model weights, or `compute_dtype=torch.bfloat16`: the engine's choice on CUDA
  for bf16 autocast and for `rollout.dtype=bfloat16`, see `posttrain.rollout.engine.select_backend`): the
  fused weights, the residual stream, every matmul and the KV cache are in the half dtype, as in the HF
  forward of a bf16 model. fp32 where accuracy needs it: RMSNorm statistics (x / hypot(|x|, c) computed in
  fp32, rounded once), RoPE (fp32 complex multiply: `view_as_complex` has no bf16, and fp32 is more exact than
  HF's bf16 cos/sin), attention (`F.scaled_dot_product_attention` with the additive key mask, the rep query
  heads of a kv head as its query "sequence": fp32 scores and softmax inside the fused kernel; explicit half
  matmuls rounded the scores to bf16, further from fp32 log-probs than HF's bf16 forward:
  docs/results-archive.md, "Figures once kept in code comments"), the logits
  handed to the sampler (the head's half output widened to fp32), sampling and log-probs. Folded norm
  weights are rounded once with the matrix they scale (HF rounds the normed activations instead): logits
  within bf16 rounding of the HF bf16 forward (tested). No packed oneDNN weights for half compute; on CPU
  bf16 compute works but is slow (bf16 elementwise work).
- Static decode step (`start(..., static=True)`, `step()`; the engine's path on CUDA): one function,
  `decode_static(tok, pos, col)`, whose shapes never change within a micro-batch: every row of the
  micro-batch is computed each step (no compaction), attention runs over the whole preallocated cache width
  (rounded up to STATIC_COLS, so micro-batches with different prompt lengths share one shape) with an
  additive key mask that is -inf for columns not yet written (the cache is zero-initialised, so masked
  columns are finite and never make NaN), and the write column, positions and input token are device tensors
  (`index_copy_` / `index_fill_` / `index_select`), so the step needs no host value and allocates nothing on
  the host. On CUDA (`CUDA_GRAPHS`, env POSTTRAIN_CUDA_GRAPHS=0 turns it off) the step is captured once per
  (rows, cache width) into a `torch.cuda.CUDAGraph` after a warm-up on a side stream, and each step is one
  replay (a decode step of a small model is otherwise ~30 layers x ~15 kernel launches). The captured
  buffers (cache, key mask, inputs, logits) are kept with the graph (`GRAPH_CACHE` shapes, least recently
  used dropped; `drop_graphs()` frees them) and reused by later calls; `load` writes every weight and bias
  in place, so a graph stays valid across weight refreshes (a changed tensor address or a regrown RoPE
  table is detected and recaptured). If capture raises for any reason, the same function runs eagerly
  (warned once). On CPU the function runs eagerly (tests compare it with `decode`).
Agreement with the HF forward: fp32 logits equal within 1e-4 (tested: prefill and decode, left-padded);
bf16 weights: logits within bf16 rounding (tested against the fp32 path and against HF's bf16 forward).
Not thread-safe: one `generate` at a time per model.
"""
from __future__ import annotations

import logging
import math
import os
from collections import OrderedDict

import torch
import torch.nn.functional as F

from .support import HALF_DTYPES
from .support import effective_weight as _weight
from .support import linear_bias as _linear_bias
from .support import rope_cis, rope_pair_order


# ----------------------------------------------------------------------------- packed weights (CPU)
# oneDNN's linear on weights reordered once into its blocked layout (torch.ops.mkldnn: the kernels
# torch.compile's CPU freezing uses) skips the per-call repacking a plain matmul does, which dominates at
# decode sizes (measured on SmolLM2: docs/results-archive.md, "Lean forwards" and "Figures once kept in code
# comments").
# POSTTRAIN_ENGINE_PACK=0 (or PACK = False) keeps plain matmuls; where the ops are missing or a
# probe disagrees with F.linear, plain matmuls are used.
PACK = os.environ.get("POSTTRAIN_ENGINE_PACK", "1").strip().lower() not in ("0", "false", "no", "off")
PACK_BATCH_HINT = 16  # rows the layout is tuned for (any row count works: decode shrinks, prefill is long)
# Narrower models multiply plain: there the oneDNN call's fixed cost outweighs the repacking it saves (packed /
# plain tokens/s by hidden size and batch: docs/results-archive.md, "Lean forwards" and "Figures once kept in
# code comments").
PACK_MIN_HIDDEN = 512
_PACK_OK: dict = {}

log = logging.getLogger(__name__)

# ----------------------------------------------------------------------------- static decode step (CUDA graphs)
CUDA_GRAPHS = os.environ.get("POSTTRAIN_CUDA_GRAPHS", "1").strip().lower() not in ("0", "false", "no", "off")
STATIC_COLS = 64  # the static step's cache width is rounded up to a multiple of this (shared graph shapes)
GRAPH_CACHE = 4  # captured (rows, width) shapes kept per model, least recently used dropped
_graph_warned = False


def pack(w: torch.Tensor) -> torch.Tensor:
    """A dense (out, in) CPU weight -> the packed (oneDNN) tensor `LeanLlama._lin` multiplies by."""
    return torch.ops.mkldnn._reorder_linear_weight(w, PACK_BATCH_HINT)


def pack_available(dtype: torch.dtype) -> bool:
    """Whether packed CPU weights of `dtype` work here: the ops exist and a probe equals F.linear (fp32: within
    fp32 rounding; bf16: within bf16 rounding). Probed once per dtype."""
    if not PACK:
        return False
    if dtype not in _PACK_OK:
        try:
            g = torch.Generator().manual_seed(0)
            w, x, b = torch.randn(24, 40, generator=g), torch.randn(5, 40, generator=g), torch.randn(24, generator=g)
            ref = F.linear(x, w, b)
            got = LeanLlama._lin(x, pack(w.to(dtype)), b)
            tol = 1e-4 if dtype == torch.float32 else 0.1
            _PACK_OK[dtype] = got.dtype == x.dtype and bool(((got - ref).abs() <= tol * ref.abs().max()).all())
        except (RuntimeError, AttributeError, NotImplementedError):  # no mkldnn build, or no kernel for dtype
            _PACK_OK[dtype] = False
    return _PACK_OK[dtype]


class LeanLlama:
    """Llama-family decoder over a preallocated KV cache (see module docstring)."""

    name = "lean"
    PREFILL_CHUNK_COST = 64  # fixed cost of one prefill chunk, in prompt tokens (op overhead)
    PREFILL_MAX_SPAN = 64  # prompts per prefill chunk, at most
    PREFILL_MAX_MASK = 1 << 22  # bound on chunk * Tp * Tp attention-mask entries

    def __init__(self, model, weight_dtype: torch.dtype | None = None, compute_dtype: torch.dtype | None = None):
        """weight_dtype: of the fused matrices (None: the compute dtype; bf16 with fp32 compute = compressed
        weights). compute_dtype: of activations and KV cache (None: the model's; a half dtype computes
        natively in it, and then the weights are in it too)."""
        if hasattr(model, "peft_config"):  # LoRA: base + adapter deltas fused below (`_weight`)
            model = model.get_base_model()
        cfg = model.config
        base = model.model
        self.device = _weight(model.lm_head).device
        self.dtype = compute_dtype or _weight(model.lm_head).dtype  # activations, residual stream, KV cache
        self.half = self.dtype in HALF_DTYPES  # native half compute (module docstring)
        self.weight_dtype = wdt = self.dtype if self.half else (weight_dtype or self.dtype)  # fused matrices
        att0 = base.layers[0].self_attn
        self.D = D = getattr(att0, "head_dim", None) or cfg.hidden_size // cfg.num_attention_heads
        self.H = H = cfg.num_attention_heads
        self.Hkv = Hkv = getattr(cfg, "num_key_value_heads", None) or H
        self.rep = H // Hkv
        self.d = d = cfg.hidden_size
        self.n_layers = len(base.layers)
        self.inter = inter = _weight(base.layers[0].mlp.gate_proj).shape[0]
        V = _weight(model.lm_head).shape[0]
        rot = base.rotary_emb
        self.inv_freq = rot.inv_freq.detach().float().clone()
        self.attention_scaling = float(getattr(rot, "attention_scaling", 1.0))
        # Per head, q/k rows go from half-split order (x_i, x_{i+D/2} are a RoPE pair) to interleaved
        # order, so RoPE is one complex multiply; q.k is unchanged by permuting both the same way. One row
        # index does it for the concatenated [q; k; v] bias (v rows stay in place); the weights are
        # written through a strided view instead (`load`).
        self._qkv_rows = torch.cat([rope_pair_order(H, D), rope_pair_order(Hkv, D) + H * D,
                                    torch.arange(Hkv * D) + (H + Hkv) * D]).to(self.device)

        def eps_const(norm):  # sqrt(d * eps): the norm's epsilon once sqrt(d) is folded into the next matrix
            return torch.tensor(math.sqrt(d * float(norm.variance_epsilon)), device=self.device,
                                dtype=torch.float32 if self.half else self.dtype)  # half: fp32 statistics

        # Packed weights (CPU): oneDNN's blocked layout for its linear kernel, made once per `load`.
        self.packed = self.device.type == "cpu" and d >= PACK_MIN_HIDDEN and not self.half and pack_available(wdt)

        def buf(rows, cols_):  # (out, in): a dense matrix `load` writes, or a placeholder it replaces (packed)
            shape = (rows, cols_)
            return torch.empty(shape if not self.packed else (0, 0), device=self.device, dtype=wdt), shape

        NH = H + 2 * Hkv
        self.layers, self._shapes = [], []
        for layer in base.layers:  # (c1, qkv_w, qkv_b, o_w, o_b, c2, gu_w, gu_b, inter, down_w, down_b)
            (qkv, s_qkv), (o, s_o), (gu, s_gu), (down, s_down) = \
                buf(NH * D, d), buf(d, H * D), buf(2 * inter, d), buf(d, inter)
            self.layers.append([eps_const(layer.input_layernorm), qkv, None, o, None,
                                eps_const(layer.post_attention_layernorm), gu, None, inter, down, None])
            self._shapes.append({1: s_qkv, 3: s_o, 6: s_gu, 9: s_down})
        self.cf = eps_const(base.norm)
        self.head_w, self._head_shape = buf(V, d)  # (V, d)
        self.head_b = None
        self.V = V
        self.load(model)
        self._bound = -1
        self._cis = None
        self._states: OrderedDict = OrderedDict()  # (rows, cols) -> _Static with a captured graph (CUDA)
        self._graph_failed = False  # a capture raised: this decoder steps eagerly from then on
        self.st = None

    @torch.no_grad()
    def load(self, model) -> None:
        """(Re)write the fused weights from `model`'s current parameters: each matrix is one strided multiply
        (RoPE row order, norm weight and softmax scale at once) into its buffer, in place, so refreshing after
        every optimizer step is cheap; packed, each is then reordered into oneDNN's layout (one more pass;
        its cost: docs/results-archive.md, "Figures once kept in code comments") from a scratch matrix of its
        shape."""
        if hasattr(model, "get_base_model"):  # peft model: base + adapter deltas (`_weight`)
            model = model.get_base_model()
        base = model.model
        d, H, Hkv, D = self.d, self.H, self.Hkv, self.D
        bias = _linear_bias

        def fold(norm):  # RMSNorm weight * sqrt(d), to scale the columns (inputs) of the next matrix
            return norm.weight.detach().float() * math.sqrt(d)

        def pairs(w, heads, g, out):  # w (heads*D, d) half-split rows -> out (heads*D, d) interleaved, * g (columns)
            src = w.view(heads, 2, D // 2, d).transpose(1, 2)  # (heads, D/2, 2, d)
            torch.mul(src, g.view(1, 1, 1, d), out=out.view(heads, D // 2, 2, d))

        scratch: dict = {}

        def dest(fused, i, shape):  # the dense (out, in) matrix to write slot i into
            if not self.packed:
                return fused[i]
            if shape not in scratch:
                scratch[shape] = torch.empty(shape, device=self.device, dtype=self.weight_dtype)
            return scratch[shape]

        def done(fused, i, w):  # packed: the written matrix, reordered (replaces the previous packed copy)
            if self.packed:
                fused[i] = pack(w)

        def put(fused, i, b):  # a bias in the compute dtype, written in place where the previous load left one
            if b is None:  # (so captured CUDA graphs keep reading the right address)
                fused[i] = None
                return
            b = b.to(self.dtype)
            cur = fused[i]
            if cur is not None and cur.shape == b.shape and cur.dtype == b.dtype and cur.device == b.device:
                cur.copy_(b)
            else:
                fused[i] = b.clone()

        for layer, fused, shapes in zip(base.layers, self.layers, self._shapes):
            a, m = layer.self_attn, layer.mlp
            g1 = fold(layer.input_layernorm)
            g2 = fold(layer.post_attention_layernorm)
            sc = float(getattr(a, "scaling", D ** -0.5))  # softmax scale, folded into q
            qkv_w = dest(fused, 1, shapes[1])  # (NH*D, d)
            pairs(_weight(a.q_proj).float(), H, g1 * sc, qkv_w[:H * D])
            pairs(_weight(a.k_proj).float(), Hkv, g1, qkv_w[H * D:(H + Hkv) * D])
            torch.mul(_weight(a.v_proj).float(), g1[None, :], out=qkv_w[(H + Hkv) * D:])
            done(fused, 1, qkv_w)
            if bias(a.q_proj) is not None:
                row_scale = torch.ones(len(self._qkv_rows), device=self.device)
                row_scale[:H * D] = sc
                put(fused, 2, torch.cat([bias(a.q_proj), bias(a.k_proj), bias(a.v_proj)]).float()
                    .index_select(0, self._qkv_rows) * row_scale)
            else:
                fused[2] = None
            o_w = dest(fused, 3, shapes[3])
            o_w.copy_(_weight(a.o_proj))  # (copy_ and mul(out=) round to a bf16 buffer)
            done(fused, 3, o_w)
            put(fused, 4, bias(a.o_proj))
            gu_w, inter = dest(fused, 6, shapes[6]), fused[8]
            torch.mul(_weight(m.gate_proj).float(), g2[None, :], out=gu_w[:inter])
            torch.mul(_weight(m.up_proj).float(), g2[None, :], out=gu_w[inter:])
            done(fused, 6, gu_w)
            put(fused, 7, None if bias(m.gate_proj) is None else torch.cat([bias(m.gate_proj), bias(m.up_proj)]))
            down_w = dest(fused, 9, shapes[9])
            down_w.copy_(_weight(m.down_proj))
            done(fused, 9, down_w)
            put(fused, 10, bias(m.down_proj))
        self.embed = base.embed_tokens.weight.detach()  # (V, d), the live parameter (no copy)
        head = [self.head_w]
        head_w = dest(head, 0, self._head_shape)
        torch.mul(_weight(model.lm_head).float(), fold(base.norm)[None, :], out=head_w)
        done(head, 0, head_w)
        self.head_w = head[0]
        head_b = [self.head_b]
        put(head_b, 0, bias(model.lm_head))
        self.head_b = head_b[0]

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _norm(x, c):
        """RMSNorm without its weight (folded into the next matrix): x / sqrt(|x|^2 + d*eps) (* sqrt(d) folded).
        Half x: computed in fp32, rounded once."""
        if x.dtype in HALF_DTYPES:
            xf = x.float()
            return (xf / torch.hypot(torch.linalg.vector_norm(xf, dim=-1, keepdim=True), c)).to(x.dtype)
        return x / torch.hypot(torch.linalg.vector_norm(x, dim=-1, keepdim=True), c)

    @staticmethod
    def _rotate(x, cis):
        """RoPE on interleaved pairs: x (N, n, D), cis (N, 1, D/2) complex -> (N, n, D) in x's dtype (half x:
        rotated in fp32, rounded once; `view_as_complex` has no bf16)."""
        N, n, D = x.shape
        if x.dtype in HALF_DTYPES:
            z = torch.view_as_complex(x.float().view(N, n, D // 2, 2))
            return torch.view_as_real(z * cis).view(N, n, D).to(x.dtype)
        return torch.view_as_real(torch.view_as_complex(x.reshape(N, n, D // 2, 2)) * cis).view(N, n, D)

    def _embed(self, tok):  # (N,) -> (N, d) in the compute dtype (bf16 compute of fp32 weights: a cast)
        x = F.embedding(tok, self.embed)
        return x if x.dtype == self.dtype else x.to(self.dtype)

    @staticmethod
    def _lin(x, w, b):
        """x @ w.T + b, w (out, in) dense or packed; compressed (bf16) weights: a bf16 matmul, fp32 out."""
        if w.is_mkldnn:
            if w.dtype != x.dtype:
                y = torch.ops.mkldnn._linear_pointwise(x.to(w.dtype), w, None, "none", [], "").to(x.dtype)
                return y if b is None else y.add_(b)
            return torch.ops.mkldnn._linear_pointwise(x, w, b, "none", [], "")
        if w.dtype != x.dtype:
            y = F.linear(x.to(w.dtype), w).to(x.dtype)
            return y if b is None else y.add_(b)
        return F.linear(x, w, b)

    @staticmethod
    def _acc(x, a, w):
        """x += a @ w.T in place (the residual stream; o_proj and down_proj)."""
        if w.is_mkldnn:
            return x.add_(LeanLlama._lin(a, w, None))
        if w.dtype != x.dtype:
            return x.add_(F.linear(a.to(w.dtype), w))
        return x.addmm_(a, w.t())

    @staticmethod
    def dense(w: torch.Tensor) -> torch.Tensor:
        """A fused weight as a dense (out, in) tensor (a packed one converted back; for inspection and tests)."""
        return w.to_dense() if w.is_mkldnn else w

    def _rope_table(self, max_pos: int) -> torch.Tensor:
        """(max_pos, D/2) complex: attention_scaling * (cos + i sin), computed as LlamaRotaryEmbedding does."""
        return rope_cis(self.inv_freq, self.attention_scaling, torch.arange(max_pos, device=self.device))

    def _mlp(self, x, layer):  # x (N, d) -> x + mlp(norm(x))
        _, _, _, _, _, c2, gu_w, gu_b, inter, down_w, down_b = layer
        gu = self._lin(self._norm(x, c2), gu_w, gu_b)  # (N, 2I)
        x = self._acc(x, F.silu(gu[:, :inter]).mul_(gu[:, inter:]), down_w)  # (N, d)
        return x if down_b is None else x + down_b

    def _logits(self, x):  # (N, d) -> (N, V) in the compute dtype (the engine widens half logits to fp32)
        return self._lin(self._norm(x, self.cf), self.head_w, self.head_b)

    # ------------------------------------------------------------------ engine interface
    def start(self, rows: int, cols: int, max_pos: int, static: bool = False) -> None:
        """Allocate the cache for `rows` rows and `cols` columns, positions < max_pos. static: for `step()`
        (cols rounded up to STATIC_COLS, a zeroed cache, keys masked until written; on CUDA a captured graph)."""
        n, Hkv, D = len(self.layers), self.Hkv, self.D
        if self._cis is None or self._cis.shape[0] < max_pos:  # grows (doubling), kept across calls
            self._cis = self._rope_table(max(max_pos, 256, 2 * (0 if self._cis is None else self._cis.shape[0])))
        self.cis = self._cis
        self.st = None
        if static:
            cols = -(-cols // STATIC_COLS) * STATIC_COLS
            self.rows, self.cols = rows, cols
            st = self._static_state(rows, cols)
            self.st = st
            self.k, self.v, self.key_bias = st.k, st.v, st.key_bias
            st.k.zero_()  # (the warm-up before a capture wrote into them; a reused state holds the last batch)
            st.v.zero_()
            st.key_bias.fill_(float("-inf"))  # every key masked until prefill / a step writes it
            self.kc = self.vc = None
            self._bound = -1
            return
        self.k = torch.empty(n, rows, Hkv, cols, D, device=self.device, dtype=self.dtype)
        self.v = torch.empty(n, rows, Hkv, cols, D, device=self.device, dtype=self.dtype)
        if self.half:  # no complex bf16: rotated keys are written as reals
            self.kc = self.vc = None
        else:
            self.kc = torch.view_as_complex(self.k.view(n, rows, Hkv, cols, D // 2, 2))  # complex views
            self.vc = torch.view_as_complex(self.v.view(n, rows, Hkv, cols, D // 2, 2))
        # Additive key mask per (row, kv head): 0 for real keys, -inf for prompt padding.
        self.key_bias = torch.zeros(rows, Hkv, 1, cols, device=self.device, dtype=self.dtype)
        self.rows, self.cols = rows, cols
        self._bound = -1

    def release(self) -> None:
        """Drop the KV cache (the fused weights stay for the next call; so do captured graphs and their
        buffers, see `drop_graphs`)."""
        self.k = self.v = self.kc = self.vc = self.key_bias = self.cis = self._views = self._bias = self.st = None
        self._bound = -1

    def drop_graphs(self) -> None:
        """Free the captured CUDA graphs and the caches they own (the next static `start` captures again)."""
        self._states.clear()

    def _bind(self, B: int) -> None:
        """Per-layer views of the first B cache rows, rebuilt only when B changes (finished rows dropped)."""
        Hkv, D, cols = self.Hkv, self.D, self.cols
        if self.half:  # real views of k / v where the fp32 path writes through complex ones
            self._views = [(self.k[li, :B], self.v[li, :B], self.k[li, :B].view(B * Hkv, cols, D).transpose(1, 2),
                            self.v[li, :B].view(B * Hkv, cols, D)) for li in range(len(self.layers))]
        else:
            self._views = [(self.kc[li, :B], self.vc[li, :B], self.k[li, :B].view(B * Hkv, cols, D).transpose(1, 2),
                            self.v[li, :B].view(B * Hkv, cols, D)) for li in range(len(self.layers))]
        self._bias = self.key_bias[:B].view(B * Hkv, 1, cols)
        self._bound = B

    def prefill(self, ids, valid, pos, row_of):
        """ids/valid/pos (U, Tp) for the unique prompts (left-padded, sorted by length for best results);
        row_of (B,) prompt of each row, non-decreasing. Returns next-token logits for each row (B, V)."""
        U, Tp = ids.shape
        B = row_of.shape[0]
        self.key_bias[:B, :, :, :Tp] = torch.where(valid[row_of], 0.0, float("-inf"))[:, None, None, :]
        out = torch.empty(B, self.V, device=self.device, dtype=self.dtype)
        starts = torch.searchsorted(row_of, torch.arange(U + 1, device=row_of.device)).tolist()
        lens = valid.sum(-1).tolist()
        for u0, u1, width in self._prefill_chunks(lens):
            r0, r1 = starts[u0], starts[u1]
            c0 = Tp - width
            if c0:  # cache columns left of this chunk's window: finite zeros under a -inf mask
                self.k[:, r0:r1, :, :c0] = 0
                self.v[:, r0:r1, :, :c0] = 0
            out[r0:r1] = self._prefill_chunk(ids[u0:u1, c0:], valid[u0:u1, c0:], pos[u0:u1, c0:],
                                             row_of[r0:r1] - u0, r0, c0)
        return out

    def _prefill_chunks(self, lens: list[int]) -> list[tuple[int, int, int]]:
        """Split consecutive prompts into chunks (u0, u1, width), each padded only to its own longest
        prompt: minimises padded tokens + PREFILL_CHUNK_COST per chunk (a chunk's fixed op overhead in
        tokens), by dynamic programming over chunks of at most PREFILL_MAX_SPAN prompts."""
        U = len(lens)
        best = [0.0] + [float("inf")] * U
        arg = [0] * (U + 1)
        for j in range(1, U + 1):
            w = 0
            for i in range(j - 1, max(-1, j - 1 - self.PREFILL_MAX_SPAN), -1):
                w = max(w, lens[i])
                if (j - i) * w * w > self.PREFILL_MAX_MASK and i < j - 1:
                    break
                c = best[i] + (j - i) * w + self.PREFILL_CHUNK_COST
                if c < best[j]:
                    best[j], arg[j] = c, i
        chunks, j = [], U
        while j > 0:
            i = arg[j]
            chunks.append((i, j, max(lens[i:j])))
            j = i
        return chunks[::-1]

    def _prefill_chunk(self, ids, valid, pos, local_rows, r0, c0):
        U, Tp = ids.shape
        N = U * Tp
        B = local_rows.shape[0]
        H, Hkv, D = self.H, self.Hkv, self.D
        identity = B == U
        rows, cols = slice(r0, r0 + B), slice(c0, c0 + Tp)
        causal = torch.ones(Tp, Tp, dtype=torch.bool, device=self.device).tril()
        eye = torch.eye(Tp, dtype=torch.bool, device=self.device)
        allowed = causal[None] & (valid[:, None, :] | eye[None])  # (U, Tp, Tp); pad queries see themselves
        attn_bias = torch.zeros(U, 1, Tp, Tp, device=self.device, dtype=self.dtype)
        attn_bias.masked_fill_(~allowed[:, None], float("-inf"))
        cis = self.cis.index_select(0, pos.reshape(-1))[:, None]  # (N, 1, D/2)
        x = self._embed(ids.reshape(-1))  # (N, d)
        for li, layer in enumerate(self.layers):
            c1, qkv_w, qkv_b, o_w, o_b = layer[:5]
            qkv = self._lin(self._norm(x, c1), qkv_w, qkv_b).view(N, H + 2 * Hkv, D)
            qk = self._rotate(qkv[:, :H + Hkv], cis).view(U, Tp, H + Hkv, D).transpose(1, 2)  # (U, H+Hkv, Tp, D)
            q, k = qk[:, :H], qk[:, H:]
            v = qkv[:, H + Hkv:].view(U, Tp, Hkv, D).transpose(1, 2)  # (U, Hkv, Tp, D)
            if identity:
                self.k[li, rows, :, cols] = k
                self.v[li, rows, :, cols] = v
            else:
                self.k[li, rows, :, cols] = k.index_select(0, local_rows)
                self.v[li, rows, :, cols] = v.index_select(0, local_rows)
            last = li == len(self.layers) - 1
            if last:  # only the last position's output is needed from the last layer
                q, bias_l = q[:, :, -1:], attn_bias[:, :, -1:]
                x = x.view(U, Tp, self.d)[:, -1]
            else:
                bias_l = attn_bias
            a = self._attend(q, k, v, bias_l)  # (U, H, Tq, D)
            x = self._acc(x, a.transpose(1, 2).reshape(x.shape[0], H * D), o_w)  # in place (last layer: a view)
            if o_b is not None:
                x = x + o_b
            x = self._mlp(x, layer)
        logits = self._logits(x)  # (U, V)
        return logits if identity else logits.index_select(0, local_rows)

    def _attend(self, q, k, v, bias):
        """Prefill attention, q (U, H, Tq, D) already scaled, k/v (U, Hkv, Tk, D), bias (U, 1, Tq, Tk) additive.
        Explicit matmuls: faster than CPU SDPA at these sizes (docs/results-archive.md, "Lean forwards"); GQA by
        grouping q heads per kv head."""
        U, H, Tq, D = q.shape
        rep = self.rep
        q = q.reshape(U, self.Hkv, rep * Tq, D)
        if self.half:  # fused SDPA: fp32 scores and softmax inside (module docstring)
            Tk = k.shape[2]
            mask = bias[:, :, None].expand(U, 1, rep, Tq, Tk).reshape(U, 1, rep * Tq, Tk)
            return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, scale=1.0).view(U, H, Tq, D)
        s = torch.matmul(q, k.transpose(-1, -2)).view(U, self.Hkv, rep, Tq, -1)  # (U, Hkv, rep, Tq, Tk)
        s = torch.softmax(s.add_(bias[:, :, None]), -1).view(U, self.Hkv, rep * Tq, -1)
        return torch.matmul(s, v).view(U, H, Tq, D)

    def decode(self, tok, pos, col: int):
        """tok (B, 1) long, pos (B,) positions, col: cache column of this token -> logits (B, V)."""
        B = tok.shape[0]
        if B != self._bound:
            self._bind(B)
        T = col + 1
        H, Hkv, D, rep = self.H, self.Hkv, self.D, self.rep
        NH, BH, HD = H + 2 * Hkv, B * Hkv, H * D
        cis = self.cis.index_select(0, pos)[:, None]  # (B, 1, D/2) complex
        bias = self._bias[:, :, :T]  # (B*Hkv, 1, T)
        x = self._embed(tok.view(B))  # (B, d)
        if self.half:
            return self._decode_half(x, cis, bias, col)
        split = (H, Hkv, Hkv)
        norm, hypot, bmm, softmax, mul, silu = torch.linalg.vector_norm, torch.hypot, torch.bmm, torch.softmax, \
            torch.mul, F.silu
        lin, acc = self._lin, self._acc
        for layer, (kc, vc, kT, vv) in zip(self.layers, self._views):
            c1, qkv_w, qkv_b, o_w, o_b, c2, gu_w, gu_b, inter, down_w, down_b = layer
            h = x / hypot(norm(x, 2, -1, True), c1)
            qkv = lin(h, qkv_w, qkv_b)  # (B, NH*D)
            zq, zk, zv = torch.view_as_complex(qkv.view(B, NH, D // 2, 2)).split_with_sizes(split, 1)  # (B, ., D/2)
            q = torch.view_as_real(zq * cis).view(BH, rep, D)  # roped q (softmax scale folded in)
            mul(zk, cis, out=kc[:, :, col])  # roped k straight into the cache
            vc[:, :, col] = zv
            s = softmax(torch.baddbmm(bias, q, kT[:, :, :T]), -1)  # (B*Hkv, rep, T): scores + key mask
            acc(x, bmm(s, vv[:, :T]).view(B, HD), o_w)  # residual += attn @ Wo, in place
            if o_b is not None:
                x = x + o_b
            h = x / hypot(norm(x, 2, -1, True), c2)
            gu = lin(h, gu_w, gu_b)  # (B, 2I)
            g, u = gu.split_with_sizes((inter, inter), 1)  # (B, I) each
            acc(x, silu(g).mul_(u), down_w)
            if down_b is not None:
                x = x + down_b
        return self._logits(x)  # (B, V)

    def _decode_half(self, x, cis, bias, col: int):
        """`decode` in a half dtype (module docstring): x (B, d) embedded tokens, cis (B, 1, D/2); the key mask is
        read as (B, Hkv, 1, T) for SDPA (`bias` is its (B*Hkv, 1, T) view, unused)."""
        B = x.shape[0]
        T = col + 1
        H, Hkv, D, rep = self.H, self.Hkv, self.D, self.rep
        HD = H * D
        lin, acc, nrm = self._lin, self._acc, self._norm
        mask = self.key_bias[:B, :, :, :T]  # (B, Hkv, 1, T)
        for layer, (kk, vk, _, _) in zip(self.layers, self._views):
            c1, qkv_w, qkv_b, o_w, o_b, c2, gu_w, gu_b, inter, down_w, down_b = layer
            qkv = lin(nrm(x, c1), qkv_w, qkv_b).view(B, H + 2 * Hkv, D)  # (B, NH, D)
            qk = self._rotate(qkv[:, :H + Hkv], cis)  # (B, H+Hkv, D) roped (fp32 inside)
            q = qk[:, :H].reshape(B, Hkv, rep, D)  # a kv head's rep query heads as its "sequence"
            kk[:, :, col] = qk[:, H:]
            vk[:, :, col] = qkv[:, H + Hkv:]
            a = F.scaled_dot_product_attention(q, kk[:, :, :T], vk[:, :, :T], attn_mask=mask, scale=1.0)
            acc(x, a.reshape(B, HD), o_w)  # residual += attn @ Wo, in place
            if o_b is not None:
                x = x + o_b
            x = self._mlp(x, layer)  # x + mlp(norm(x)), down_proj accumulated in place
        return self._logits(x)  # (B, V)

    def select(self, order: list[int], col: int) -> None:
        """New active rows = old rows `order` (old active count B0 -> len(order)); cache columns < col valid."""
        holes = [i for i, o in enumerate(order) if o != i]
        if holes:
            src = torch.tensor([order[i] for i in holes], device=self.device)
            dst = torch.tensor(holes, device=self.device)
            self.k[:, dst, :, :col] = self.k[:, src, :, :col]
            self.v[:, dst, :, :col] = self.v[:, src, :, :col]
            self.key_bias[dst, :, :, :col] = self.key_bias[src, :, :, :col]
        self._bound = -1

    # ------------------------------------------------------------------ static decode step (module docstring)
    def decode_static(self, tok, pos, col):
        """One decode step with static shapes over all `rows` rows and the whole cache width: tok (rows, 1) long,
        pos (rows,) long positions, col (1,) long cache column, all device tensors -> logits (rows, V) fp32.
        Writes k / v at column `col` (`index_copy_`) and unmasks it (`index_fill_`); no host value is read."""
        B, cols = self.rows, self.cols
        H, Hkv, D, rep, d = self.H, self.Hkv, self.D, self.rep, self.d
        NH, BH, HD = H + 2 * Hkv, B * Hkv, H * D
        half = self.half
        cis = self.cis.index_select(0, pos)[:, None]  # (B, 1, D/2) complex
        self.key_bias.index_fill_(3, col, 0.0)  # the column written this step becomes visible to every row
        bias = self.key_bias.view(BH, 1, cols)  # (B*Hkv, 1, cols): 0 written keys, -inf padding / unwritten
        x = self._embed(tok.view(B))  # (B, d)
        lin, acc, nrm = self._lin, self._acc, self._norm
        for li, layer in enumerate(self.layers):
            c1, qkv_w, qkv_b, o_w, o_b, c2, gu_w, gu_b, inter, down_w, down_b = layer
            kl, vl = self.k[li], self.v[li]  # (B, Hkv, cols, D)
            qkv = lin(nrm(x, c1), qkv_w, qkv_b).view(B, NH, D)
            qk = self._rotate(qkv[:, :H + Hkv], cis)  # (B, H+Hkv, D)
            q = qk[:, :H].reshape(BH, rep, D)  # roped q (softmax scale folded in)
            kl.index_copy_(2, col, qk[:, H:, None])  # (B, Hkv, 1, D) into column col
            vl.index_copy_(2, col, qkv[:, H + Hkv:, None])
            if half:  # fused SDPA (fp32 scores and softmax inside): q (B, Hkv, rep, D) over the whole cache
                a = F.scaled_dot_product_attention(q.view(B, Hkv, rep, D), kl, vl, attn_mask=self.key_bias, scale=1.0)
            else:
                s = torch.softmax(torch.baddbmm(bias, q, kl.view(BH, cols, D).transpose(1, 2)), -1)  # (BH, rep, cols)
                a = torch.bmm(s, vl.view(BH, cols, D))  # (B*Hkv, rep, D)
            acc(x, a.reshape(B, HD), o_w)  # residual += attn @ Wo, in place
            if o_b is not None:
                x = x + o_b
            x = self._mlp(x, layer)  # x + mlp(norm(x)), down_proj accumulated in place
        return self._logits(x.view(B, d)).float()  # (B, V) fp32 for the sampler

    def step(self) -> torch.Tensor:
        """`decode_static` on the static state's input buffers `st.tok`, `st.pos`, `st.col` (the caller writes
        them): one graph replay when captured, else eager. -> logits (rows, V) fp32, overwritten by the next step."""
        st = self.st
        if st.graph is not None:
            st.graph.replay()
            return st.logits
        return self.decode_static(st.tok, st.pos, st.col)

    def _tensors(self) -> tuple:
        """Addresses of every tensor the step reads besides the cache (a captured graph holds them)."""
        ts = [self.embed, self.cf, self.head_w, self.head_b, self._cis]
        for layer in self.layers:
            ts += [t for t in layer if isinstance(t, torch.Tensor)]
        return tuple(None if t is None else t.data_ptr() for t in ts)

    def _static_state(self, rows: int, cols: int) -> "_Static":
        """The static buffers for (rows, cols): on CUDA with CUDA_GRAPHS, kept with a graph captured over them
        (recaptured when a weight's address or the RoPE table changed); else fresh, for eager steps."""
        graphs = CUDA_GRAPHS and self.device.type == "cuda" and not self._graph_failed
        key = (rows, cols)
        st = self._states.get(key) if graphs else None
        if st is not None and st.ptrs == self._tensors():
            self._states.move_to_end(key)
            return st
        if st is not None:
            del self._states[key]
            st = None
        st = _Static(self, rows, cols)
        if graphs:
            self._capture(st)
            if st.graph is not None:
                self._states[key] = st
                while len(self._states) > GRAPH_CACHE:
                    self._states.popitem(last=False)
        return st

    def _capture(self, st: "_Static") -> None:
        """Capture `decode_static` over st's buffers (torch.cuda.graphs recipe: warm-up on a side stream, then
        capture). Any failure leaves st.graph None: the step runs eagerly (warned once per process)."""
        global _graph_warned
        self.k, self.v, self.key_bias, self.rows, self.cols = st.k, st.v, st.key_bias, st.rows, st.cols
        st.col.fill_(st.cols - 1)
        try:
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side):
                for _ in range(2):
                    self.decode_static(st.tok, st.pos, st.col)
            torch.cuda.current_stream(self.device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                st.logits = self.decode_static(st.tok, st.pos, st.col)
            st.graph, st.ptrs = graph, self._tensors()
        except Exception as e:  # noqa: BLE001  (never crash generation: the same step runs eagerly)
            st.graph = st.logits = None
            self._graph_failed = True
            try:
                torch.cuda.synchronize(self.device)
            except Exception:  # noqa: BLE001
                pass
            if not _graph_warned:
                _graph_warned = True
                log.warning("lean decode: CUDA graph capture failed (%s: %s); decoding eagerly",
                            type(e).__name__, str(e).splitlines()[0] if str(e) else "")


class _Static:
    """Device buffers of the static decode step for one (rows, cols) shape: the zeroed KV cache, the key mask,
    the step's inputs tok (rows, 1), pos (rows,), col (1,), and on CUDA the captured graph and its logits."""

    def __init__(self, lean: LeanLlama, rows: int, cols: int):
        dev, dt = lean.device, lean.dtype
        n, Hkv, D = len(lean.layers), lean.Hkv, lean.D
        self.rows, self.cols = rows, cols
        self.k = torch.zeros(n, rows, Hkv, cols, D, device=dev, dtype=dt)  # (L, B, Hkv, cols, D)
        self.v = torch.zeros(n, rows, Hkv, cols, D, device=dev, dtype=dt)
        self.key_bias = torch.full((rows, Hkv, 1, cols), float("-inf"), device=dev, dtype=dt)
        self.tok = torch.zeros(rows, 1, dtype=torch.long, device=dev)
        self.pos = torch.zeros(rows, dtype=torch.long, device=dev)
        self.col = torch.zeros(1, dtype=torch.long, device=dev)
        self.graph = self.logits = self.ptrs = None
