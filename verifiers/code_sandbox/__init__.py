"""Code verifier: run model-written Python against unit tests in a sandboxed process.

    CodeVerifier().check(completion, {"tests": "def check(candidate): ...", "entry_point": "f"})
    CodeVerifier(partial_credit=True).check(completion, {"tests": ["assert f(1) == 2", ...]})
    python -c "from posttrain.verifiers.code_sandbox import measure_overhead; print(measure_overhead())"

Reference format
----------------
A dict with
- ``tests``: either a string in HumanEval style that defines ``check(candidate)`` (one
  test: the harness calls ``check(<entry_point>)``), or a list of statement strings,
  usually ``assert f(1) == 2``; each item is one test (partial credit counts them). An
  item that is a single bare expression is asserted truthy.
- ``entry_point`` (optional): the function handed to ``check``. Default: the last
  function the candidate defines at top level.
- ``setup`` (optional): code run before the candidate's code and before the tests
  (imports, helpers).
- ``prompt`` (optional, HumanEval's convention): when the extracted code does not define
  ``entry_point`` it is taken as the continuation of ``prompt`` (a body); when it does, the
  prompt still goes first (its imports and helpers such as HumanEval/32's ``poly`` stay
  available; the candidate's later definition wins), or only its import lines if the prompt
  is not valid Python on its own. A prompt that is valid Python also runs on the tests'
  side, so the helpers the tests call are the reference's own: a candidate that redefines
  ``poly`` to make ``check`` pass changes nothing.

Names the tests use must come from ``setup``, the prompt, the tests themselves, or be
functions the candidate defines (those become proxies to the candidate process).

Code extraction: fenced blocks tagged python/py/python3 (else untagged fences; an
unterminated last fence counts); the submission is the *last* block that defines something
at top level (``def``/``class``), skipping blocks that only call or print (usage examples)
or only define ``test_*``/``check`` (the model's own tests). So a corrected version after a
draft wins, and so does a retraction: "no wait, here is the right one" followed by other
code submits that other code. Without fences: the raw text after any ``</think>``.
Candidate code runs with ``__name__ == "candidate"``, so ``if __name__ == "__main__":``
demos do not run.

How a run works (integrity)
---------------------------
The candidate never shares an interpreter with the tests. The harness process P starts
in the sandbox, sets its rlimits, makes itself non-dumpable (no ptrace, no
/proc/P/mem or /proc/P/fd by same-uid processes) and forks the candidate process C
*before* it reads its task from stdin, so C's memory never holds the tests or the
per-run nonce. C closes P's stdin and stdout (the result channel), then loads the
candidate code and serves calls over a private pipe pair. P runs the reference tests
in its own interpreter, with each candidate function replaced by a proxy: arguments go
to C, and C's return value comes back as a pickle that P loads with an unpickler which
accepts only plain data (builtins, OrderedDict, Counter, deque, defaultdict, Fraction,
Decimal, datetime). In-place changes to list/dict/set/bytearray arguments are copied
back. P counts the tests it ran and passed, and writes one result line (a Python literal,
read with ``ast.literal_eval``) with the parent's nonce to its stdout; the parent accepts a pass only when that line carries the nonce
and ``passed == total ==`` the number of tests in the reference. So these all score 0:
``sys.exit(0)`` / ``os._exit(0)`` / ``raise SystemExit`` (no result from C), printing a
fake success line (C's output goes to the log only), redefining ``check`` / ``print`` /
builtins or patching "the harness" (that happens in C's interpreter, not P's), returning
an object whose ``__eq__`` is always true (not plain data), writing to P's result pipe
(C does not hold it), killing P (no result).

Limits of this design: tests that pass callables or other non-data values *to* the
candidate, or that call methods on candidate-defined classes, are not supported (the
call fails with a clear message); return values must be plain data.

Sandbox modes (``CodeVerifier().mode`` / ``.sandbox``, ``sandbox_mode()``, ``details["mode"]`` / ``["sandbox"]``)
--------------------------------------------------------------------------------------------------------------
``Verdict.details["sandbox"]``, ``CodeVerifier().sandbox`` and the last line of
``python -m posttrain.verifiers.cli list`` (``posttrain verifiers``) say which one ran: "bubblewrap",
"fallback" or "fallback (no namespaces)"; ``details["isolation"]`` says it in words.

- ``"bwrap"`` / "bubblewrap" (bubblewrap present and user namespaces allowed): new user, pid,
  net, ipc, uts, mount and cgroup namespaces; a read-only view of /usr, /etc, /bin, /sbin,
  /lib* and the interpreter's prefix only (not ``/``: datasets, home directories and the
  checkout stay invisible; ``bind_root=True`` binds all of ``/`` read-only instead); a fresh
  size-limited tmpfs at /tmp whose /tmp/work is cwd and HOME (nothing is written to the host
  disk), a size-limited /dev/shm, a minimal read-only /dev; ``--die-with-parent``, nested user
  namespaces disabled, no capabilities; the harness is the namespace's pid 1
  (``--as-pid-1``), so the candidate cannot kill it and everything else dies with it. As
  root, bwrap itself is started as the per-run uid.
- ``"rlimits"`` with namespaces / "fallback" (no usable bubblewrap; as root, with
  util-linux ``unshare``, ``namespaces=True``): the util-linux binary runs
  ``unshare --net --pid --fork --kill-child --mount-proc --ipc --uts`` (new net, pid, mount,
  ipc and uts namespaces; no user or cgroup namespace) and starts the harness as root, as
  the new pid namespace's pid 1. Before it reads its task, the harness (harness.py,
  ``enter_view``) builds the same view as bubblewrap's with mount(2) in its private mount
  namespace (propagation private, so nothing reaches the host): a new root on a small tmpfs
  holding read-only, nosuid binds of /usr, /etc, /bin, /sbin, /lib* and the interpreter's
  prefix, the new pid namespace's /proc (read-only), a /dev with only null, zero, full,
  random, urandom and tty, and fresh tmpfs at /tmp (``tmpfs_mb``, 16384 inodes; /tmp/work
  is cwd and HOME) and /dev/shm (at most 16 MB); read-only through one
  ``mount_setattr(AT_RECURSIVE)`` (Linux >= 5.12; else one bind remount per mount), then
  ``pivot_root`` into it and the host's tree is detached (``chroot`` on architectures
  whose syscall number it does not know). ``bind_root=True``: every host mount read-only
  instead, with the fresh tmpfs over /tmp and /dev/shm. Then it drops to the per-run uid
  (``setgroups([])``, ``setresgid``, ``setresuid``; it checks that no capability is left)
  and continues as in every mode. Nothing of a run is written to the host disk. The
  view costs about 1 ms per check (some 30 mount calls in the harness).
- ``"rlimits"`` without namespaces / "fallback (no namespaces)" (not root, no ``unshare``,
  or ``namespaces=False``): a fresh host temp dir (0700, owned by the run's uid) as
  cwd/HOME/TMPDIR, rlimits, a new session; as root, a per-run uid. Afterwards (as root)
  every process of the run's uid is killed (``kill(-1)`` as that uid), the work dir is
  emptied through the fd opened when it was created, and the uid's entries at the top of
  /tmp, /var/tmp and /dev/shm are removed. The removal never follows a symlink (names are
  opened relative to their parent's fd with O_NOFOLLOW and checked against the inode),
  never leaves the tree or crosses a mount, touches nothing above the work dir, and
  chmods nothing except, when not root, a directory of the run's own tree that the
  candidate made unreadable.

All modes: scrubbed environment (PATH=/usr/local/bin:/usr/bin:/bin, HOME, TMPDIR,
LANG, PYTHONHASHSEED=0 for determinism, PYTHONDONTWRITEBYTECODE); ``python -S -s -B``
with the cwd removed from ``sys.path``; rlimits set by the harness before it reads its
task: CPU seconds, address space, processes (counted per sandbox inside bwrap's user
namespace, per run uid otherwise), file size, open files, no core files;
``no_new_privs``; a wall-clock deadline enforced by P (partial results survive) and by
the parent, which kills the whole process group (``start_new_session`` + ``killpg``);
the candidate's stdout/stderr is kept as a bounded rolling tail, and after 8 MiB the pipe is
closed (further writes fail with EPIPE). Nothing is left behind: when ``check`` returns,
the sandbox's processes are gone and its files removed (except, without namespaces, what
the candidate wrote in world-writable directories other than the top of /tmp, /var/tmp and
/dev/shm), and the mode, owner and mtime of /tmp, /var/tmp, /dev/shm are as before (tests:
tests/verifiers/test_sandbox_host_integrity.py).

Reasons: "passed", "failed k/n tests", "syntax error", "no code found", "code too long",
"timeout", "timeout (cpu limit)", "killed (memory)", "error on load (ExcType)",
"exited early (...)", "crashed (SIGNAME)", "harness killed (no result)",
"protocol violation". Details: mode, sandbox, isolation, python, tests_passed, tests_total,
failures (test, label, error with the values compared), stderr_tail, and error/traceback
for load errors. A reference that fails to load in the sandbox raises ValueError; a
harness failure (our bug or a broken machine) raises RuntimeError.

Non-root user. Linux does not enforce RLIMIT_NPROC for root, so as root every run gets
its own uid from 2**30 + (pid % 2**22) * 256 + slot (unique among live processes; never
in /etc/passwd). The switch is done in the child, by util-linux ``setpriv`` (bubblewrap,
fallback without namespaces) or by the harness itself once its view is built (fallback),
rather than by ``Popen(user=...)``, which would force a fork() of the verifier process:
tens of ms per candidate in a trainer holding GBs of memory. The project's Python may live somewhere other users cannot read (here:
/root/.pyenv), so the sandbox interpreter is the first of ``python=``, the running
interpreter, /usr/bin/python3, /usr/local/bin/python3 that the sandbox user can actually
run (probed once; ``CodeVerifier().python`` and ``details["python"]`` say which). The
harness needs only the standard library; candidates get the standard library only
(no site-packages).

Threat model
------------
The candidate is hostile: it may try to read the reference or other data, change the host,
escape, or outlast the run. What each mode isolates ("fallback" = with namespaces):

- Filesystem reads. bubblewrap and fallback: only /usr, /etc, /bin, /sbin, /lib*, the
  interpreter's prefix (bind_root: all of /), read-only, subject to the uid's permissions;
  the checkout, datasets, home directories, the host's /tmp, /var and /run are invisible.
  Fallback (no namespaces): every file the uid can read, i.e. all world-readable files of
  the host (a dataset file holding the tests included).
- Filesystem writes. bubblewrap and fallback: none on the host; only the run's own tmpfs
  /tmp and /dev/shm (size-capped, discarded). Fallback (no namespaces): its work dir, and
  everywhere its uid may write: world-writable directories and files (/tmp, /var/tmp,
  /dev/shm and any other); as root, what it leaves at the top of /tmp, /var/tmp, /dev/shm
  is removed, files elsewhere stay and world-writable files it changed stay changed;
  without root it runs as you and can change all your files.
- Network: bubblewrap and fallback: a new net namespace (loopback only). Fallback (no
  namespaces): the host network. Unix sockets reached by path are not covered by a net
  namespace: with bind_root, world-writable sockets of the host (/run/...) are reachable.
- Processes: bubblewrap and fallback: a new pid namespace (sees and signals only its own;
  the harness is pid 1; all die with it), new ipc and uts namespaces. Fallback (no
  namespaces): sees all host processes in /proc; as root its distinct uid cannot signal
  or ptrace them, without root it can signal and (if ptrace is allowed) trace yours, and a
  process that calls setsid() can outlive the run (a warning says so).
- Resources (all modes): CPU seconds, address space, processes, file size, open files,
  no core files, wall clock; tmpfs size (bubblewrap, fallback); not disk or memory
  bandwidth, the page cache, or the tmpfs' memory (charged to the host, up to tmpfs_mb).
- Uid: bubblewrap: the per-run uid (as root) or yours, inside a user namespace with no
  capabilities. Fallback: the per-run uid, no capabilities (the harness is root only while
  it builds the view, before it reads the task; candidate code never runs as root), no
  user namespace. Fallback (no namespaces): the per-run uid as root, else your own uid.
  All: ``no_new_privs``, so setuid binaries do not raise privileges.
- Always: the tests and nonce are never in C's memory; P is non-dumpable.
Not isolated in any mode: the kernel attack surface (no seccomp filter), CPU/cache timing
side channels, what /proc and the visible system files say about the machine (CPU,
memory, kernel version, load), reading world-readable files in the bound directories, and the
candidate sees each test's arguments (it must, to compute the answer). The fallback
differs from bubblewrap in having no user and no cgroup namespace (its /proc/self/cgroup
shows the host's paths), keeping the host's hostname, and letting the candidate create
nested user namespaces where the kernel allows them (bubblewrap disables them): that
gains nothing on the host (the view's mounts are locked read-only in a child namespace,
the host's tree is detached, /proc is read-only so no uid map can be written), but it
widens the kernel surface. Install bubblewrap where you can.

Layout (this package)
---------------------
- ``harness.py``: the sandbox-side script (P and C above). Never imported: ``sandbox.py`` reads
  its text and runs it as ``python -S -s -B -c <text> <config ints>`` inside the sandbox.
- ``sandbox.py``: the host side of a run: interpreter and bwrap/unshare probes, modes, per-run
  uids, argv builders, pipe I/O with deadlines and bounded output, cleanup.
- ``extract.py``: code extraction and reference parsing (never executes candidate code).
- ``verifier.py``: ``CodeVerifier`` (launch, verdicts) and ``measure_overhead``.
- ``audit.py``: the built-in audit problems and the hostile programs.
"""
from __future__ import annotations

from posttrain.verifiers.code_sandbox.audit import _PROBLEMS  # noqa: F401  (tests read it from here)
from posttrain.verifiers.code_sandbox.extract import extract_code
from posttrain.verifiers.code_sandbox.sandbox import _UID_BASE, _UID_SLOTS, SandboxMode, sandbox_mode  # noqa: F401
from posttrain.verifiers.code_sandbox.verifier import CodeVerifier, measure_overhead

__all__ = ["CodeVerifier", "sandbox_mode", "measure_overhead", "extract_code"]
