"""Run an episode's tool calls off the sampling thread, concurrently, under a wall-clock limit per call.

    runner = ToolRunner(workers=8)
    pending = runner.submit(env.tool_functions(), calls, limits)   # returns at once
    ...                                                            # the engine keeps decoding other rows
    results = pending.poll()                                       # None until every call is answered
    runner.close()

Every call ends as a `ToolResult` within its limit, never as an exception, and its content is text any tokenizer
takes (at most `MAX_CONTENT_CHARS` characters, plus a truncation marker; an unpaired surrogate, which a sandboxed
program may print, is written as its escape `\\ud800`):
- a call the parser marked malformed, an unknown tool, arguments the function's signature refuses, and calls past
  `limits.max_calls_per_turn` are answered at once, without running anything;
- an exception in the tool is `error: ExceptionType: message` (kind "exception");
- a call still running `limits.tool_timeout_s` after it was submitted is answered `error: timeout after N s`
  (kind "timeout") and abandoned: Python cannot stop a thread, so a hung in-process tool keeps its worker thread
  (the pool starts another for later calls, up to `max_abandoned`, then submit raises). Tools that may hang for
  good belong in a subprocess: the python tool runs in the code sandbox, which kills its process at its limit.
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Sequence

from posttrain.verifiers.envs.base import Limits, ToolCall, ToolResult, check_arguments

MAX_CONTENT_CHARS = 4000  # a tool's return value is cut to this many characters (the model's context is small)


def _text(value: Any) -> str:
    """What the model sees of `value` (a tool's return value or an error message): cut to MAX_CONTENT_CHARS, each
    unpaired surrogate written as its escape (a tokenizer refuses the character, and so does a UTF-8 file)."""
    text = value if isinstance(value, str) else repr(value)
    text = text.encode("utf-8", "backslashreplace").decode("utf-8")
    if len(text) > MAX_CONTENT_CHARS:
        text = text[:MAX_CONTENT_CHARS] + f"...[truncated {len(text) - MAX_CONTENT_CHARS} characters]"
    return text


def _run(fn: Callable, call: ToolCall) -> ToolResult:
    t = time.perf_counter()
    try:
        out = fn(**call.arguments)
    except Exception as e:  # the model's arguments broke the tool: the model is told, the step goes on
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        return ToolResult(call, _text(f"error: {type(e).__name__}: {msg}"[:500]), "exception", time.perf_counter() - t)
    return ToolResult(call, _text(out), None, time.perf_counter() - t)


def immediate_result(call: ToolCall, tools: dict[str, Callable]) -> ToolResult | None:
    """The answer to a call that must not run (malformed, unknown tool, bad arguments), or None."""
    if call.error:
        return ToolResult(call, _text(f"error: {call.error}"), "malformed")
    if call.name not in tools:
        names = ", ".join(sorted(tools)) or "none"
        return ToolResult(call, _text(f"error: unknown tool {call.name!r}; the tools are: {names}"), "unknown_tool")
    why = check_arguments(tools[call.name], call.arguments or {})
    if why:
        return ToolResult(call, _text(f"error: bad arguments for {call.name}: {why}"), "bad_arguments")
    return None


class Pending:
    """The calls of one assistant turn, in flight. `poll()` returns their results (in call order) once every call is
    answered or timed out, else None; `wait()` blocks until then."""

    def __init__(self, calls: list[ToolCall], slots: list[ToolResult | Future], deadline: float, timeout_s: float):
        self.calls, self.slots, self.deadline, self.timeout_s = calls, slots, deadline, timeout_s
        self.abandoned = 0

    def poll(self, now: float | None = None) -> list[ToolResult] | None:
        now = time.monotonic() if now is None else now
        futures = [s for s in self.slots if isinstance(s, Future)]
        if now < self.deadline and not all(f.done() for f in futures):
            return None
        out = []
        for call, s in zip(self.calls, self.slots):
            if not isinstance(s, Future):
                out.append(s)
            elif s.done():
                out.append(s.result())
            else:
                s.cancel()
                self.abandoned += 1
                out.append(ToolResult(call, f"error: timeout after {self.timeout_s:g} s", "timeout", self.timeout_s))
        return out

    def wait(self) -> list[ToolResult]:
        while True:
            got = self.poll()
            if got is not None:
                return got
            futures = [s for s in self.slots if isinstance(s, Future) and not s.done()]
            if futures:
                try:
                    futures[0].result(timeout=max(0.0, self.deadline - time.monotonic()))
                except Exception:  # timeouts and cancellations: poll() decides
                    pass


class ToolRunner:
    """A thread pool for tool calls (see the module docstring). Not shared across processes; close it when done."""

    def __init__(self, workers: int = 8, max_abandoned: int = 64):
        self.workers, self.max_abandoned = workers, max_abandoned
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="posttrain-tool")
        self._lock = threading.Lock()
        self._abandoned: list[Future] = []  # timed-out calls still running in their threads
        self._stuck_here = 0  # of them, those holding a thread of the current pool

    def submit(self, tools: dict[str, Callable], calls: Sequence[ToolCall], limits: Limits) -> Pending:
        calls = list(calls)
        slots: list[ToolResult | Future] = []
        self._reap()
        for k, call in enumerate(calls):
            if k >= limits.max_calls_per_turn:
                slots.append(ToolResult(call, f"error: too many tool calls in one turn (at most "
                                              f"{limits.max_calls_per_turn})", "too_many_calls"))
                continue
            now = immediate_result(call, tools)
            slots.append(now if now is not None else self._pool.submit(_run, tools[call.name], call))
        return Pending(calls, slots, time.monotonic() + limits.tool_timeout_s, limits.tool_timeout_s)

    def abandon(self, pending: Pending) -> None:
        """Remember `pending`'s calls that outlived their limit; a pool with a thread stuck in each is replaced."""
        with self._lock:
            late = [s for s in pending.slots if isinstance(s, Future) and not s.done()]
            self._abandoned += late
            self._stuck_here += len(late)
            if len(self._abandoned) > self.max_abandoned:
                raise RuntimeError(f"{len(self._abandoned)} tool calls are still running past their time limit; a "
                                   "tool hangs without end (run it in a subprocess, e.g. through the code sandbox)")
            if self._stuck_here >= self.workers:  # every thread may be stuck: later calls get a fresh pool
                self._pool.shutdown(wait=False, cancel_futures=False)
                self._pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="posttrain-tool")
                self._stuck_here = 0

    def _reap(self) -> None:
        with self._lock:
            self._abandoned = [f for f in self._abandoned if not f.done()]

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> "ToolRunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
