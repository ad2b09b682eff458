"""A second device on a CPU-only machine, for catching device-placement bugs without a GPU.

`VirtualDevice()` is a context manager (a `TorchFunctionMode`) that splits the CPU in two, the way a CUDA
machine is split into host and device:
- "device" tensors: every tensor put on `DEVICE` (`torch.device("cpu", 0)`, which the mode reports as
  `t.device` for them): `.to(DEVICE)` / `.to(device=DEVICE)` / `.cuda()`, a factory called with `device=DEVICE`,
  a `*_like` of a device tensor, every result of an op on a device tensor (views, grads and `.data` included),
  and a Parameter whose `.data` was set to one (`nn.Module.to(DEVICE)`);
- "host" tensors: everything else: factories without `device=` (`torch.tensor([...])`, `torch.zeros(n)`),
  tokenizer outputs, `.cpu()` / `.to("cpu")` results.
An op that mixes a device tensor with a host tensor of one or more dimensions (any host tensor in a `cat` /
`stack`) raises `DeviceMismatch`, as CUDA raises "Expected all tensors to be on the same device". What CUDA
allows stays allowed: 0-dim host tensors (scalars) beside device tensors in arithmetic, `copy_` across the two, host index tensors into a device tensor (`x[idx]`),
basic-index assignment (`host[a:b] = device_tensor`, a copy). Reading a device tensor back (`.item()`, `float()`,
`int()`, `bool()`, `.tolist()`, `.cpu()`, `.numpy()`) counts as a host sync (`syncs`); it is allowed.

`Accelerator.device` (what every trainer places its model and batches on) and `posttrain.runtime.default_device()`
report `DEVICE` inside the mode (`patch_accelerate`), so a run through the CLI puts its model there and must move its batches there too.

Limits: only Python-level torch calls are seen (torch function modes do not see ops inside C++ kernels,
which run on one device anyway); `torch.device("cpu", 0)` compares unequal to `torch.device("cpu")`, so code
that tests `device == torch.device("cpu")` sees a non-CPU device, as it would on a GPU; the mode's
bookkeeping makes a step a few times slower.
"""
from __future__ import annotations

import collections
import contextlib
import traceback

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten, tree_map
from torch.utils.weak import WeakTensorKeyDictionary

DEVICE = torch.device("cpu", 0)
HOST = torch.device("cpu")


class DeviceMismatch(RuntimeError):
    """An op mixed tensors of the virtual device and of the host (CUDA: "Expected all tensors to be on the same
    device")."""


_FACTORIES = {torch.zeros, torch.ones, torch.full, torch.empty, torch.tensor, torch.as_tensor, torch.arange,
              torch.randn, torch.rand, torch.randint, torch.eye, torch.linspace, torch.logspace, torch.scalar_tensor,
              torch.empty_strided, torch.randperm, torch.tril_indices, torch.triu_indices, torch.normal}
_LIKE = {torch.zeros_like, torch.ones_like, torch.full_like, torch.empty_like, torch.rand_like, torch.randn_like,
         torch.randint_like}
_JOINS = {"cat", "concat", "concatenate", "stack", "hstack", "vstack", "dstack", "column_stack"}
_SYNCS = {"item", "__float__", "__int__", "__bool__", "__index__", "tolist", "numpy", "__len__"}
_DEVICE_DESC = torch._C.TensorBase.__dict__["device"]
_DATA_DESC = torch._C.TensorBase.__dict__["data"]
_META = {"_has_compatible_shallow_copy_type", "is_same_size", "__get__", "copy_", "__deepcopy__"}  # no arithmetic across the two
_DEVICE_ARG_METHODS = {"new_zeros", "new_ones", "new_full", "new_empty", "new_tensor"}


def _as_device(x) -> torch.device | None:
    if isinstance(x, torch.device):
        return x
    if isinstance(x, str):
        try:
            return torch.device(x)
        except RuntimeError:
            return None
    if isinstance(x, int) and not isinstance(x, bool):
        return torch.device("cuda", x)
    return None


def _is_device(d: torch.device | None) -> bool:
    """A requested device that means the accelerator: DEVICE itself or any CUDA device."""
    return d is not None and (d == DEVICE or d.type == "cuda")


def _real(x):
    """The device argument torch gets: HOST for the virtual device (or CUDA); anything else (cpu, meta) as given."""
    return HOST if not isinstance(x, torch.dtype) and _is_device(_as_device(x)) else x


_ON_DEVICE = WeakTensorKeyDictionary()


class VirtualDevice(TorchFunctionMode):
    """See the module docstring. `syncs`: host reads of device tensors seen; `strict=False` records mismatches in
    `mismatches` instead of raising (to list them all)."""

    def __init__(self, strict: bool = True):
        super().__init__()
        self.on_device = _ON_DEVICE  # shared by every guard: a tensor put on the device stays there (caches)
        self.syncs = 0
        self.sync_sites: collections.Counter = collections.Counter()  # where the host reads happened
        self.strict = strict
        self.mismatches: list[str] = []
        self._stack = contextlib.ExitStack()

    # ------------------------------------------------------------ bookkeeping
    def tag(self, t):
        if isinstance(t, torch.Tensor):
            self.on_device[t] = True
        return t

    def untag(self, t):
        if isinstance(t, torch.Tensor) and t in self.on_device:
            del self.on_device[t]
        return t

    def placed(self, t: torch.Tensor) -> bool:
        """On the virtual device, or on a real accelerator (on a GPU machine the trainers' models are there)."""
        if t in self.on_device:
            return True
        with torch._C.DisableTorchFunction():
            return t.device.type not in ("cpu", "meta")

    def put(self, model: torch.nn.Module) -> torch.nn.Module:
        """Put a module's parameters, buffers and grads on the virtual device (what `model.to(DEVICE)` does)."""
        for p in list(model.parameters()) + list(model.buffers()):
            self.tag(p)
        return model

    def __enter__(self):
        self._stack.enter_context(patch_accelerate())
        return super().__enter__()

    def __exit__(self, *exc):
        try:
            return super().__exit__(*exc)
        finally:
            self._stack.close()

    # ------------------------------------------------------------ the check
    def _mismatch(self, name: str, dev: list, host: list) -> None:
        msg = (f"device guard: {name} at {_caller()} mixes tensors on the device {[tuple(t.shape) for t in dev][:3]} "
               f"and on the host {[tuple(t.shape) for t in host][:3]} (CUDA: 'Expected all tensors to be on the same "
               "device')")
        if self.strict:
            raise DeviceMismatch(msg)
        self.mismatches.append(msg)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", str(func))
        owner = getattr(func, "__self__", None)
        if name == "__get__" and owner is _DEVICE_DESC:
            return DEVICE if self.placed(args[0]) else func(*args)
        if name == "__set__" and owner is _DATA_DESC:  # param.data = x (nn.Module._apply): the parameter is where x is
            out = func(*args)
            (self.tag if self.placed(args[1]) else self.untag)(args[0])
            return out
        if func in _FACTORIES:
            d = _as_device(kwargs.get("device"))
            out = func(*args, **{**kwargs, **({"device": _real(d)} if d is not None else {})})
            return tree_map(self.tag, out) if _is_device(d) else out
        if func in _LIKE:
            d = _as_device(kwargs.get("device"))
            out = func(*args, **{**kwargs, **({"device": _real(d)} if d is not None else {})})
            on = _is_device(d) if d is not None else self.placed(args[0])
            return self.tag(out) if on else out
        if name in ("to", "cuda", "cpu") and args and isinstance(args[0], torch.Tensor):
            return self._to(func, name, args, kwargs)
        if name in _DEVICE_ARG_METHODS and "device" in kwargs:
            d = _as_device(kwargs["device"])
            out = func(*args, **{**kwargs, "device": _real(d)})
            return self.tag(out) if _is_device(d) else out

        tensors = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        dev = [t for t in tensors if self.placed(t)]
        if name in _SYNCS:
            if dev:
                self._sync()
            return func(*args, **kwargs)
        # CUDA takes a 0-dim host tensor beside device tensors in arithmetic, not in a concatenation
        host = [t for t in tensors if not self.placed(t) and (t.dim() > 0 or name in _JOINS)]
        if dev and host and not self._allowed(func, name, args):
            self._mismatch(name, dev, host)
        out = func(*args, **kwargs)
        if name == "__deepcopy__":  # a copy is where its source is (the memo may hold other tensors)
            return self.tag(out) if self.placed(args[0]) else out
        if dev and name != "__set__":
            out = tree_map(self.tag, out)
        return out

    def _allowed(self, func, name, args) -> bool:
        """The mixes CUDA accepts."""
        if name in _META:
            return True
        if name == "__getitem__":  # a host index into a device tensor is fine; a device index into a host one is not
            return self.placed(args[0])
        if name == "__setitem__":
            self_t, index, value = args
            idx = [t for t in tree_flatten(index)[0] if isinstance(t, torch.Tensor)]
            if any(self.placed(t) for t in idx) and not self.placed(self_t):
                return False
            if not idx:  # basic indexing: a copy_ into a view, across devices
                return True
            return not isinstance(value, torch.Tensor) or value.dim() == 0 or \
                self.placed(value) == self.placed(self_t)
        return False

    def _to(self, func, name, args, kwargs):
        t = args[0]
        if name == "cuda":
            return t if self.placed(t) else self.tag(t.clone())
        if name == "cpu":
            if self.placed(t):
                self._sync()
            out = args[0] if not self.placed(t) else args[0].clone()
            return self.untag(out) if out is not t else out
        target = None
        for a in list(args[1:]) + [kwargs.get("device")]:
            if isinstance(a, torch.Tensor):
                target = DEVICE if self.placed(a) else HOST
                break
            d = _as_device(a) if not isinstance(a, torch.dtype) else None
            if d is not None:
                target = d
                break
        clean_args = [a.dtype if isinstance(a, torch.Tensor) else _real(a) for a in args[1:]]
        clean_kwargs = {k: (_real(v) if k == "device" else v) for k, v in kwargs.items()}
        out = func(t, *clean_args, **clean_kwargs)
        if target is None:  # a dtype change only: stays where it is
            return self.tag(out) if self.placed(t) else out
        on = _is_device(target)
        if on == self.placed(t):
            return self.tag(out) if on else out
        if out is t:  # a real move makes a new tensor; the source stays where it was
            out = t.clone()
        if not on:
            self._sync()
        return self.tag(out) if on else self.untag(out)

    def _sync(self) -> None:
        self.syncs += 1
        self.sync_sites[_caller()] += 1


def _caller() -> str:
    """The innermost frame of the project's own code (posttrain/, verifiers/, scripts/) that made the call."""
    for frame in reversed(traceback.extract_stack()[:-3]):
        path = frame.filename.replace("\\", "/")
        for top in ("/posttrain/", "/verifiers/", "/scripts/"):
            if top in path and "/tests/" not in path and "site-packages" not in path:
                return f"{top[1:]}{path.split(top, 1)[1]}:{frame.lineno}"
    return "?"


@contextlib.contextmanager
def patch_accelerate():
    """`Accelerator.device` (what the trainers place models and batches on) and `runtime.default_device()` (what
    commands without an Accelerator use) are `DEVICE` where they would be the CPU."""
    from accelerate import Accelerator

    from posttrain import runtime

    prop, default = Accelerator.__dict__["device"], getattr(runtime, "default_device", None)

    def device(self):
        d = prop.fget(self)
        return DEVICE if d.type == "cpu" else d

    Accelerator.device = property(device)
    if default is not None:
        runtime.default_device = lambda: DEVICE if default().type == "cpu" else default()
    try:
        yield
    finally:
        Accelerator.device = prop
        if default is not None:
            runtime.default_device = default
