"""Score completions under hard limits: worker processes, a wall-clock limit per check, crash isolation.

    from posttrain.verifiers import VerifierPool, get_verifier, score_batch
    verdicts = score_batch("math", completions, answers, workers=2, timeout_s=5)
    with VerifierPool(workers=4) as pool:          # a training loop keeps one pool
        for step in ...:
            verdicts = pool.score(verifier, completions, answers)

Guarantees, for every check:
- It runs under a wall-clock limit (`timeout_s`, default: the verifier's `timeout_s`). The limit
  is enforced by the calling process watching its workers, never with signal.alarm, so it works
  from any thread. A check that overruns is scored Verdict(0, "timeout") and its worker is
  killed (SIGKILL) and replaced; the rest of that worker's chunk is rescheduled.
- A worker that dies (segfault, os._exit, the OOM killer) scores its current item
  Verdict(0, "crashed: <how>") and is replaced. A MemoryError raised inside a check (see
  `memory_limit_mb`) is treated the same way: exhausting memory is what the input did.
- Any other exception raised by the verifier is a bug in the verifier (the contract in
  verifiers/base.py: bad model output is a score of 0, not an exception). It propagates as
  `VerifierError` naming the verifier and the item index, with the original exception as
  `__cause__` (its remote traceback in `.remote_traceback`). The batch stops; the pool's busy
  workers are replaced so no stale work leaks into the next batch.
- The batch never hangs: each item ends as a verdict, a timeout or a crash within its limit.

Throughput: items go to workers in chunks (default: n / (4 x workers), at most 64 per chunk),
and each worker streams one small result message per item back, so the per-item deadline is
exact while process round-trips stay per chunk. The verifier is pickled once per batch and
installed once per worker (its `warmup()` runs then, outside the per-item limit).

In-process fast path. Verifiers with `in_process = True` (format, length: regex/length work that
cannot run away on its own), and every verifier when `workers=0`, run in the calling process
on a helper thread; the caller waits at most `timeout_s` per item. Python cannot kill a thread,
so a check that overruns there keeps running in the background: it is scored "timeout", the
helper thread is abandoned, and the pool stops running that verifier in-process (the rest of
the batch and later batches go to worker processes). That is why sympy-based math never takes
this path by default: `9**9**9**9` inside a C call cannot be interrupted by anything but a kill.

Start method: "fork" on Linux (fast to start and to replace a hung worker), "spawn" elsewhere;
override with `start_method=` or the env var POSTTRAIN_VERIFIER_START_METHOD. With "fork", the
pool runs `verifier.warmup()` once in the calling process too, so replacement workers start
warm. Forking a process that runs other threads (torch, tokenizers) is safe here because
workers only run verifier code; use "forkserver" or "spawn" if a verifier touches such
libraries. Workers exit on their own when the parent process dies.

A pool is not thread-safe for concurrent batches: calls are serialised with a lock.
"""
from __future__ import annotations

import atexit
import collections
import hashlib
import math
import multiprocessing as mp
import os
import pickle
import queue
import signal
import sys
import threading
import time
import traceback
import weakref
from multiprocessing.connection import wait as _mp_wait
from typing import Any, Sequence

from posttrain.verifiers.base import Verdict, Verifier

INSTALL_TIMEOUT_S = 120.0  # unpickling the verifier + warmup() in a fresh worker
MAX_INSTALLED = 32  # verifiers kept per worker (oldest installed dropped first, same order in the parent)


class VerifierError(RuntimeError):
    """A verifier raised (a bug in the verifier or a malformed reference), re-raised by the runner."""

    def __init__(self, verifier: str, index: int | None, exc_type: str, message: str,
                 remote_traceback: str | None = None):
        where = f"on item {index}" if index is not None else "while loading in a worker"
        super().__init__(f"verifier {verifier!r} raised {exc_type} {where}: {message}")
        self.verifier = verifier
        self.index = index
        self.exc_type = exc_type
        self.message = message
        self.remote_traceback = remote_traceback


def default_workers() -> int:
    """Worker processes used when none are given: the CPU count, at most 8."""
    return max(1, min(os.cpu_count() or 1, 8))


def _default_start_method() -> str:
    env = os.environ.get("POSTTRAIN_VERIFIER_START_METHOD")
    if env:
        return env
    if sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods():
        return "fork"
    return "spawn"


def _resolve(verifier: Verifier | str) -> Verifier:
    if isinstance(verifier, str):
        from posttrain.verifiers.registry import get_verifier

        return get_verifier(verifier)
    if not isinstance(verifier, Verifier):
        raise TypeError(f"expected a Verifier or a registry spec string, got {type(verifier).__name__}")
    return verifier


def _vname(verifier: Verifier) -> str:
    return verifier.name or type(verifier).__name__


def _describe_exit(exitcode: int | None) -> str:
    if exitcode is None:
        return "worker died"
    if exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"worker exited with code {exitcode}"


def _check_result(result: Any, verifier: Verifier) -> Verdict:
    if not isinstance(result, Verdict):
        raise TypeError(f"check() returned {type(result).__name__}, expected a Verdict")
    return result


# --------------------------------------------------------------------------------------
# Worker process
# --------------------------------------------------------------------------------------


def _exc_message(e: BaseException) -> tuple[str, str, str, bytes | None]:
    tb = "".join(traceback.format_exception(type(e), e, e.__traceback__))
    try:
        blob = pickle.dumps(e)
        pickle.loads(blob)
    except Exception:
        blob = None
    return type(e).__name__, str(e), tb, blob


def _worker_main(conn, parent_end, memory_limit_mb: int | None, ppid: int) -> None:
    """Loop: install verifiers, score chunks, stream one message per item back."""
    if parent_end is not None:
        parent_end.close()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    if memory_limit_mb:
        try:
            import resource

            limit = int(memory_limit_mb) * 1024 * 1024
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        except (ImportError, ValueError, OSError):
            pass
    installed: collections.OrderedDict[str, Verifier] = collections.OrderedDict()  # mirrored by _Worker.installed
    while True:
        try:
            while not conn.poll(1.0):
                if os.getppid() != ppid:
                    return  # the parent is gone
            msg = conn.recv()
        except (EOFError, OSError, KeyboardInterrupt):
            return
        kind = msg[0]
        if kind == "stop":
            return
        if kind == "install":
            _, key, payload, files = msg
            try:
                from posttrain.verifiers.registry import _import_file_module

                for modname, path in files:
                    if modname not in sys.modules:
                        _import_file_module(modname, path)
                verifier = pickle.loads(payload)
                verifier.warmup()
                installed[key] = verifier
                while len(installed) > MAX_INSTALLED:
                    installed.popitem(last=False)
                conn.send(("ready", key))
            except BaseException as e:  # noqa: BLE001 - reported to the parent, which raises
                conn.send(("install_error", key, *_exc_message(e)))
            continue
        if kind == "chunk":
            _, key, items = msg
            verifier = installed[key]
            for idx, completion, reference in items:
                try:
                    verdict = _check_result(verifier.check(completion, reference), verifier)
                    conn.send(("done", idx, verdict.score, verdict.reason, verdict.details))
                except MemoryError:
                    conn.send(("crash", idx, "MemoryError"))
                except BaseException as e:  # noqa: BLE001 - a verifier bug, re-raised by the parent
                    conn.send(("error", idx, *_exc_message(e)))
                    break


class _Worker:
    def __init__(self, ctx, memory_limit_mb: int | None):
        parent_end, child_end = ctx.Pipe(duplex=True)
        # with fork the child also inherits parent_end; it closes it so EOF works
        inherit = parent_end if ctx.get_start_method() == "fork" else None
        self.proc = ctx.Process(target=_worker_main, args=(child_end, inherit, memory_limit_mb, os.getpid()),
                                name="posttrain-verifier-worker", daemon=False)
        self.proc.start()
        child_end.close()
        self.conn = parent_end
        self.installed: collections.OrderedDict[str, None] = collections.OrderedDict()
        self.state = "idle"  # idle | installing | busy | dead
        self.chunk: list | None = None
        self.pos = 0
        self.deadline = math.inf

    def send(self, msg) -> bool:
        try:
            self.conn.send(msg)
            return True
        except (OSError, ValueError, BrokenPipeError):
            return False

    def kill(self) -> None:
        try:
            if self.proc.is_alive():
                self.proc.kill()
            self.proc.join(timeout=5)
        except (OSError, ValueError, AssertionError):
            pass
        try:
            self.conn.close()
        except OSError:
            pass
        self.state = "dead"

    def stop(self) -> None:
        if self.state == "idle" and self.proc.is_alive():
            self.send(("stop",))
            self.proc.join(timeout=1)
        self.kill()


_LIVE_POOLS: "weakref.WeakSet[VerifierPool]" = weakref.WeakSet()


@atexit.register
def _close_live_pools() -> None:
    for pool in list(_LIVE_POOLS):
        pool.close()


# --------------------------------------------------------------------------------------
# The pool
# --------------------------------------------------------------------------------------


class VerifierPool:
    """Persistent worker processes for scoring; reuse one across batches (e.g. every GRPO step).

    workers: worker processes (None: `default_workers()`; 0: score in the calling process).
    timeout_s: per-check wall-clock limit (None: each verifier's own `timeout_s`).
    chunk_size: items per task (None: n / (4 x workers), clamped to [1, 64]).
    memory_limit_mb: address-space cap per worker (RLIMIT_AS, POSIX); None for no cap. Note it
        counts what a forked worker inherited from the parent too.
    start_method: multiprocessing start method (see module docstring).
    """

    def __init__(self, workers: int | None = None, *, timeout_s: float | None = None,
                 chunk_size: int | None = None, memory_limit_mb: int | None = None,
                 start_method: str | None = None):
        if workers is not None and (not isinstance(workers, int) or workers < 0):
            raise ValueError(f"workers must be a non-negative int or None, got {workers!r}")
        if timeout_s is not None and not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if chunk_size is not None and (not isinstance(chunk_size, int) or chunk_size < 1):
            raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
        self.workers = default_workers() if workers is None else workers
        self.timeout_s = timeout_s
        self.chunk_size = chunk_size
        self.memory_limit_mb = memory_limit_mb
        self.start_method = start_method or _default_start_method()
        self._ctx = mp.get_context(self.start_method)
        self._pool: list[_Worker] = []
        self._lock = threading.Lock()
        self._closed = False
        self._demoted: "weakref.WeakSet[Verifier]" = weakref.WeakSet()  # in-process verifiers that overran once
        self._demoted_ids: set[int] = set()  # the same, for verifiers that cannot be weakly referenced
        self._warmed: set[str] = set()
        self.stats = {"items": 0, "timeouts": 0, "crashes": 0, "respawns": 0}
        _LIVE_POOLS.add(self)

    # -- public API ----------------------------------------------------------------
    def score(self, verifier: Verifier | str, completions: Sequence[str], references: Sequence[Any], *,
              timeout_s: float | None = None) -> list[Verdict]:
        """Verdicts for each (completion, reference) pair, in order (see module docstring)."""
        verifier = _resolve(verifier)
        completions, references = list(completions), list(references)
        if len(completions) != len(references):
            raise ValueError(f"got {len(completions)} completions but {len(references)} references")
        limit = self._limit(verifier, timeout_s)
        items = [(i, c, r) for i, (c, r) in enumerate(zip(completions, references))]
        results: list[Verdict | None] = [None] * len(items)
        with self._lock:
            if self._closed:
                raise RuntimeError("VerifierPool is closed")
            if not items:
                return []
            if self.workers == 0 or (verifier.in_process and not self._is_demoted(verifier)):
                items = self._score_in_process(verifier, items, limit, results)
            if items:
                self._score_in_workers(verifier, items, limit, results)
            self.stats["items"] += len(results)
        return results  # type: ignore[return-value]

    def score_one(self, verifier: Verifier | str, completion: str, reference: Any, *,
                  timeout_s: float | None = None) -> Verdict:
        return self.score(verifier, [completion], [reference], timeout_s=timeout_s)[0]

    def close(self) -> None:
        """Stop the workers (idle ones politely, busy ones with SIGKILL)."""
        self._closed = True
        for w in self._pool:
            w.stop()
        self._pool = []

    def __enter__(self) -> "VerifierPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass

    # -- internals -----------------------------------------------------------------
    def _limit(self, verifier: Verifier, timeout_s: float | None) -> float:
        limit = timeout_s if timeout_s is not None else (self.timeout_s if self.timeout_s is not None else verifier.timeout_s)
        if not isinstance(limit, (int, float)) or not limit > 0:
            raise ValueError(f"timeout_s must be > 0, got {limit!r}")
        return float(limit)

    def _score_in_process(self, verifier: Verifier, items: list, limit: float, results: list) -> list:
        """Score on a helper thread; return the items left over if the verifier overran."""
        out: queue.Queue = queue.Queue()
        cancel = threading.Event()

        def run() -> None:
            for idx, completion, reference in items:
                if cancel.is_set():
                    return
                try:
                    out.put((idx, True, _check_result(verifier.check(completion, reference), verifier)))
                except MemoryError:
                    out.put((idx, True, Verdict(0.0, "crashed: MemoryError")))
                except BaseException as e:  # noqa: BLE001 - re-raised in the caller
                    out.put((idx, False, e))
                    return

        helper = threading.Thread(target=run, name=f"verifier-{_vname(verifier)}", daemon=True)
        helper.start()
        for pos, (idx, _, _) in enumerate(items):
            try:
                got_idx, ok, value = out.get(timeout=limit)
            except queue.Empty:
                cancel.set()
                results[idx] = Verdict(0.0, "timeout", {"timeout_s": limit})
                self.stats["timeouts"] += 1
                rest = items[pos + 1:]
                if self.workers == 0 or not self._picklable(verifier):
                    # no worker processes to move to: go on in-process with a fresh helper thread
                    return self._score_in_process(verifier, rest, limit, results) if rest else []
                try:
                    self._demoted.add(verifier)
                except TypeError:
                    self._demoted_ids.add(id(verifier))
                return rest
            if not ok:
                raise VerifierError(_vname(verifier), got_idx, type(value).__name__, str(value),
                                    "".join(traceback.format_exception(type(value), value, value.__traceback__))) from value
            results[got_idx] = value
        return []

    def _is_demoted(self, verifier: Verifier) -> bool:
        try:
            return verifier in self._demoted
        except TypeError:
            return id(verifier) in self._demoted_ids

    @staticmethod
    def _picklable(verifier: Verifier) -> bool:
        try:
            pickle.dumps(verifier)
            return True
        except Exception:
            return False

    def _spawn(self) -> _Worker:
        return _Worker(self._ctx, self.memory_limit_mb)

    def _score_in_workers(self, verifier: Verifier, items: list, limit: float, results: list) -> None:
        name = _vname(verifier)
        try:
            payload = pickle.dumps(verifier)
        except Exception as e:
            raise TypeError(
                f"verifier {name!r} cannot be sent to worker processes ({type(e).__name__}: {e}); define it at "
                "module level (or load it as file.py:name) or score with workers=0") from e
        key = hashlib.sha1(payload).hexdigest()
        from posttrain.verifiers.registry import loaded_file_modules

        files = loaded_file_modules()
        n_workers = max(1, min(self.workers, len(items)))
        chunk = self.chunk_size or max(1, min(64, math.ceil(len(items) / (4 * n_workers))))
        pending = collections.deque(items[i:i + chunk] for i in range(0, len(items), chunk))
        if self.start_method == "fork" and key not in self._warmed:
            verifier.warmup()  # forked replacements then start warm
            self._warmed.add(key)
        self._pool = [w for w in self._pool if w.state != "dead" and w.proc.is_alive()]
        while len(self._pool) < n_workers:
            self._pool.append(self._spawn())
        remaining = sum(1 for r in results if r is None)
        # A verifier that raises: the error of the lowest item index is the one re-raised, whichever worker
        # reported first. Chunks go out in index order, so once an item raised, the chunks already out finish
        # (or raise) and pending ones of higher indices are dropped; then the lowest is raised.
        errors: list[VerifierError] = []
        try:
            while remaining:
                if errors and not pending and not any(w.state in ("busy", "installing") for w in self._pool):
                    break
                now = time.monotonic()
                for k, w in enumerate(self._pool):
                    if w.state == "dead":
                        if not pending:
                            continue
                        w = self._pool[k] = self._spawn()
                        self.stats["respawns"] += 1
                    if w.state != "idle" or not pending:
                        continue
                    if not w.proc.is_alive():  # died while idle: replace it, charge no item
                        w.kill()
                        continue
                    if key not in w.installed:
                        if w.send(("install", key, payload, files)):
                            w.state, w.deadline = "installing", now + INSTALL_TIMEOUT_S
                        else:
                            w.kill()
                        continue
                    ch = pending.popleft()
                    if w.send(("chunk", key, ch)):
                        w.state, w.chunk, w.pos, w.deadline = "busy", ch, 0, now + limit
                    else:
                        pending.appendleft(ch)
                        w.kill()
                active = [w for w in self._pool if w.state in ("installing", "busy")]
                if not active:
                    if not pending:
                        raise RuntimeError("verifier pool lost track of items (a bug in verifiers/runner.py)")
                    continue
                wait_s = max(0.0, min(w.deadline for w in active) - time.monotonic())
                ready = set(_mp_wait([w.conn for w in active] + [w.proc.sentinel for w in active], wait_s))
                for w in active:
                    broken = False
                    while True:
                        try:
                            if not w.conn.poll():
                                break
                            msg = w.conn.recv()
                        except (EOFError, OSError):
                            broken = True
                            break
                        try:
                            remaining -= self._handle(w, msg, name, limit, results, pending)
                        except VerifierError as e:
                            if e.index is None:  # the verifier did not load: nothing else can run
                                raise
                            errors.append(e)
                            lowest = min(x.index for x in errors)
                            kept = [ch for ch in pending if ch[0][0] < lowest]
                            pending.clear()
                            pending.extend(kept)
                    if broken or w.proc.sentinel in ready:
                        if not w.proc.is_alive() or broken:
                            remaining -= self._handle_death(w, name, results, pending)
                now = time.monotonic()
                for w in active:
                    if w.state in ("busy", "installing") and now >= w.deadline:
                        remaining -= self._handle_timeout(w, name, limit, results, pending)
            if errors:
                raise min(errors, key=lambda e: e.index)
        except BaseException:
            # a verifier bug or Ctrl-C: busy workers hold stale work, replace them
            for w in self._pool:
                if w.state in ("busy", "installing"):
                    w.kill()
            raise

    def _advance(self, w: _Worker, limit: float) -> None:
        w.pos += 1
        w.deadline = time.monotonic() + limit
        if w.chunk is not None and w.pos >= len(w.chunk):
            w.state, w.chunk, w.pos, w.deadline = "idle", None, 0, math.inf

    def _handle(self, w: _Worker, msg: tuple, name: str, limit: float, results: list, pending) -> int:
        kind = msg[0]
        if kind == "ready":
            w.installed[msg[1]] = None
            while len(w.installed) > MAX_INSTALLED:
                w.installed.popitem(last=False)
            w.state, w.deadline = "idle", math.inf
            return 0
        if kind == "install_error":
            _, _, etype, text, tb, blob = msg
            w.kill()
            raise VerifierError(name, None, etype, text, tb) from _load_exc(blob, tb)
        if kind == "done":
            _, idx, score, reason, details = msg
            results[idx] = Verdict(score, reason, details)
            self._advance(w, limit)
            return 1
        if kind == "crash":
            _, idx, text = msg
            results[idx] = Verdict(0.0, f"crashed: {text}")
            self.stats["crashes"] += 1
            self._advance(w, limit)
            return 1
        if kind == "error":
            _, idx, etype, text, tb, blob = msg
            w.state, w.chunk, w.pos, w.deadline = "idle", None, 0, math.inf
            raise VerifierError(name, idx, etype, text, tb) from _load_exc(blob, tb)
        raise RuntimeError(f"unexpected message from a verifier worker: {kind!r}")

    def _handle_death(self, w: _Worker, name: str, results: list, pending) -> int:
        state, chunk, pos = w.state, w.chunk, w.pos
        w.kill()
        exitcode = w.proc.exitcode
        if state == "installing":
            raise VerifierError(name, None, "WorkerDied", _describe_exit(exitcode))
        if state != "busy" or chunk is None:
            return 0
        idx = chunk[pos][0]
        results[idx] = Verdict(0.0, f"crashed: {_describe_exit(exitcode)}", {"exitcode": exitcode})
        self.stats["crashes"] += 1
        if chunk[pos + 1:]:
            pending.appendleft(chunk[pos + 1:])
        return 1

    def _handle_timeout(self, w: _Worker, name: str, limit: float, results: list, pending) -> int:
        state, chunk, pos = w.state, w.chunk, w.pos
        w.kill()
        if state == "installing":
            raise VerifierError(name, None, "TimeoutError",
                                f"did not load in a worker within {INSTALL_TIMEOUT_S:.0f}s (unpickling + warmup())")
        idx = chunk[pos][0]
        results[idx] = Verdict(0.0, "timeout", {"timeout_s": limit})
        self.stats["timeouts"] += 1
        if chunk[pos + 1:]:
            pending.appendleft(chunk[pos + 1:])
        return 1


def _load_exc(blob: bytes | None, tb: str | None) -> BaseException | None:
    if blob is None:
        return None
    try:
        exc = pickle.loads(blob)
    except Exception:
        return None
    if tb and hasattr(exc, "add_note"):
        exc.add_note("remote traceback (in the verifier worker):\n" + tb)
    return exc


# --------------------------------------------------------------------------------------
# One-shot helpers
# --------------------------------------------------------------------------------------


def score_batch(verifier: Verifier | str, completions: Sequence[str], references: Sequence[Any], *,
                workers: int | None = None, timeout_s: float | None = None) -> list[Verdict]:
    """Score a batch with a temporary pool (a training loop should keep a `VerifierPool`).

    workers=None uses `default_workers()` processes (none at all for in-process verifiers);
    workers=0 scores in the calling process (the limit then bounds the wait, not the work).
    """
    verifier = _resolve(verifier)
    completions = list(completions)
    # workers start lazily: an in-process verifier never starts one unless it overruns
    n = 0 if workers == 0 else max(1, min(workers if workers is not None else default_workers(), len(completions) or 1))
    with VerifierPool(workers=n, timeout_s=timeout_s) as pool:
        return pool.score(verifier, completions, references)


def score_one(verifier: Verifier | str, completion: str, reference: Any, *,
              timeout_s: float | None = None) -> Verdict:
    """Score one completion under the same limits (one worker process, or in-process when cheap)."""
    return score_batch(verifier, [completion], [reference], workers=1, timeout_s=timeout_s)[0]
