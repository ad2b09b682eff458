# The sandbox-side harness (processes P and C of the package docstring). It is NOT imported:
# sandbox.py reads this file's text and the sandbox runs it as
# `python -S -s -B -c <this file> <config ints>` (see CodeVerifier._config for the ints).
# It imports only C modules on the normal path (no json/re/traceback: start-up time is
# the sandbox's overhead); the task arrives as marshal data, the result leaves as a repr
# that the parent reads with ast.literal_eval.
# Standard library only, Python >= 3.8.
if __name__ != "__main__":  # importing it would fork and take over the importing process
    raise ImportError("verifiers/code_sandbox/harness.py runs only inside the sandbox (python -c); do not import it")
import os, sys
sys.path[:] = [p for p in sys.path if p not in ("", ".")]
import _pickle as pickle, _signal as signal, builtins, ctypes, io, marshal, resource, select, struct, time

CFG = dict(zip(("timeout", "cpu", "mem", "fsize", "nofile", "nproc", "max_msg", "max_failures"),
               [float(sys.argv[1])] + [int(x) for x in sys.argv[2:9]]))
DEADLINE = time.monotonic() + CFG["timeout"]
HEADER = struct.Struct(">I")
SAFE_GLOBALS = {
    ("builtins", n) for n in ("bool", "bytearray", "bytes", "complex", "dict", "float",
                              "frozenset", "int", "list", "range", "set", "slice", "str", "tuple")
} | {("collections", n) for n in ("OrderedDict", "Counter", "deque", "defaultdict")} | {
    ("fractions", "Fraction"), ("decimal", "Decimal"), ("datetime", "date"), ("datetime", "datetime"),
    ("datetime", "time"), ("datetime", "timedelta"), ("datetime", "timezone"),
}
MUTABLE = (list, dict, set, bytearray)


class Deadline(BaseException):
    pass


class Gone(BaseException):
    """The candidate process died, hung up or broke the protocol: every later call fails."""


class CandidateError(Exception):
    pass


def limit(res, soft, hard):
    cur = resource.getrlimit(res)[1]
    if cur != resource.RLIM_INFINITY:
        hard = min(hard, cur)
        soft = min(soft, hard)
    resource.setrlimit(res, (soft, hard))


def harden():
    limit(resource.RLIMIT_CORE, 0, 0)
    limit(resource.RLIMIT_CPU, CFG["cpu"], CFG["cpu"] + 1)
    limit(resource.RLIMIT_AS, CFG["mem"], CFG["mem"])
    limit(resource.RLIMIT_FSIZE, CFG["fsize"], CFG["fsize"])
    limit(resource.RLIMIT_NOFILE, CFG["nofile"], CFG["nofile"])
    if CFG["nproc"]:
        limit(resource.RLIMIT_NPROC, CFG["nproc"], CFG["nproc"])
    libc = ctypes.CDLL(None, use_errno=True)
    # PR_SET_NO_NEW_PRIVS=1, PR_SET_DUMPABLE=0 (no ptrace or /proc/P/{mem,fd} by the
    # candidate), PR_SET_PDEATHSIG=SIGKILL (die with the verifier).
    for option, value in ((38, 1), (4, 0), (1, int(signal.SIGKILL))):
        if libc.prctl(option, ctypes.c_ulong(value), ctypes.c_ulong(0), ctypes.c_ulong(0), ctypes.c_ulong(0)):
            raise OSError(ctypes.get_errno(), "prctl(%d) failed" % option)


def write_all(fd, data):
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def send(fd, obj):
    data = pickle.dumps(obj, protocol=4)
    write_all(fd, HEADER.pack(len(data)) + data)


def read_exact(fd, n, deadline):
    chunks = []
    while n:
        if deadline is not None:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([fd], [], [], left)[0]:
                raise Deadline()
        chunk = os.read(fd, min(n, 1 << 20))
        if not chunk:
            raise EOFError("pipe closed")
        chunks.append(chunk)
        n -= len(chunk)
    return b"".join(chunks)


def recv_frame(fd, deadline):
    (size,) = HEADER.unpack(read_exact(fd, HEADER.size, deadline))
    if size > CFG["max_msg"]:
        raise Gone("the candidate sent %d bytes (limit %d)" % (size, CFG["max_msg"]))
    return read_exact(fd, size, deadline)


def describe(exc):
    try:
        text = str(exc)
    except BaseException:
        text = "<unprintable>"
    name = type(exc).__name__
    return (name + ": " + text if text else name)[:400]


def test_line(exc, source):
    """ "line N: <source line>" of the innermost test frame, for failure reports."""
    tb, found = exc.__traceback__, None
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == "<tests>":
            found = tb.tb_lineno
        tb = tb.tb_next
    if found is None:
        return ""
    lines = source.splitlines()
    return " (tests line %d: %s)" % (found, lines[found - 1].strip()[:160] if 0 < found <= len(lines) else "?")


# ---------------------------------------------------------------- candidate process (C)
def child_main(rfd, wfd):
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)  # the task (tests, nonce) is still unread in P's stdin
    os.dup2(2, 1)  # fd 1 is P's result channel; candidate output goes to the log
    os.close(null)
    for fd in range(3, CFG["nofile"]):
        if fd not in (rfd, wfd):
            try:
                os.close(fd)
            except OSError:
                pass
    try:
        sys.stdout.reconfigure(line_buffering=True)
    except Exception:
        pass
    _, setup, code = pickle.loads(recv_frame(rfd, None))
    ns = {"__name__": "candidate", "__builtins__": builtins}
    try:
        exec(compile(setup, "<setup>", "exec"), ns)
    except BaseException as exc:
        send(wfd, ("setup_error", describe(exc)))
        os._exit(0)
    try:
        compiled = compile(code, "<candidate>", "exec")
    except BaseException as exc:
        send(wfd, ("syntax_error", describe(exc)))
        os._exit(0)
    try:
        exec(compiled, ns)
    except BaseException as exc:
        try:
            import traceback
            tb = "".join(traceback.format_exception(type(exc), exc, exc.__traceback__))[-1500:]
        except BaseException:
            tb = ""
        send(wfd, ("load_error", type(exc).__name__, describe(exc), tb))
        os._exit(0)
    send(wfd, ("loaded", [k for k, v in list(ns.items()) if type(v).__name__ == "function"]))
    while True:
        _, seq, name, args, kwargs = pickle.loads(recv_frame(rfd, None))
        try:
            if name not in ns:
                raise NameError("name %r is not defined" % name)
            result = ns[name](*args, **kwargs)
            mutated = [(i, a) for i, a in enumerate(args) if type(a) in MUTABLE]
            data = pickle.dumps(("ok", seq, result, mutated), protocol=4)
        except BaseException as exc:
            try:
                text = str(exc)[:400]
            except BaseException:
                text = "<unprintable>"
            data = pickle.dumps(("exc", seq, type(exc).__name__, text), protocol=4)
        write_all(wfd, HEADER.pack(len(data)) + data)


# ------------------------------------------------------------------- harness process (P)
class SafeUnpickler(pickle.Unpickler):
    def find_class(self, module, name):
        if (module, name) in SAFE_GLOBALS:
            return super().find_class(module, name)
        raise pickle.UnpicklingError("the candidate returned a non-data value (%s.%s)" % (module, name))


class Link:
    def __init__(self, pid, wfd, rfd):
        self.pid, self.wfd, self.rfd = pid, wfd, rfd
        self.seq = 0
        self.gone = None  # why the candidate process is unusable
        self.timeout = False
        self.memory = False
        self.status = None  # C's wait status once reaped

    def mark_gone(self, why):
        if self.gone is None:
            self.gone = why
        self.reap(0.2)

    def reap(self, grace):
        if self.status is not None:
            return
        end = time.monotonic() + grace
        while True:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:
                return
            if pid:
                self.status = status
                return
            if time.monotonic() >= end:
                return
            time.sleep(0.005)

    def receive(self):
        try:
            frame = recv_frame(self.rfd, DEADLINE)
        except Deadline:
            self.timeout = True
            raise
        except (EOFError, OSError) as exc:
            self.mark_gone("the candidate process exited")
            raise Gone(self.gone)
        except Gone as exc:
            self.mark_gone(str(exc))
            raise
        try:
            return SafeUnpickler(io.BytesIO(frame)).load()
        except MemoryError:
            self.memory = True
            raise
        except Exception as exc:
            return ("undecodable", describe(exc))

    def call(self, name, args, kwargs):
        if self.timeout:
            raise Deadline()
        if self.gone:
            raise Gone(self.gone)
        self.seq += 1
        try:
            data = pickle.dumps(("call", self.seq, name, args, kwargs), protocol=4)
        except Exception as exc:
            raise TypeError("a test argument cannot be sent to the sandboxed candidate: " + describe(exc))
        try:
            write_all(self.wfd, HEADER.pack(len(data)) + data)
        except OSError:
            self.mark_gone("the candidate process exited")
            raise Gone(self.gone)
        reply = self.receive()
        if not isinstance(reply, tuple) or not reply:
            self.mark_gone("protocol violation")
            raise Gone(self.gone)
        if reply[0] == "undecodable":
            # The frame was read, so the channel is still in sync: this call alone fails.
            raise CandidateError(reply[1])
        if len(reply) != 4 or reply[1] != self.seq or reply[0] not in ("ok", "exc"):
            self.mark_gone("protocol violation")
            raise Gone(self.gone)
        if reply[0] == "exc":
            tname, message = reply[2], reply[3]
            if tname == "MemoryError":
                self.memory = True
            cls = getattr(builtins, tname, None) if isinstance(tname, str) else None
            if isinstance(cls, type) and issubclass(cls, Exception):
                try:
                    raise cls(message)
                except TypeError:
                    pass
            raise CandidateError("%s: %s" % (tname, message))
        mutated = reply[3]
        if isinstance(mutated, list):
            for item in mutated:
                if not (isinstance(item, tuple) and len(item) == 2 and type(item[0]) is int):
                    continue
                i, new = item
                if 0 <= i < len(args) and type(args[i]) is type(new) and type(new) in MUTABLE and args[i] != new:
                    old = args[i]
                    if type(old) in (list, bytearray):
                        old[:] = new
                    else:
                        old.clear()
                        old.update(new)
        return reply[2]


class Candidate:
    """Stands for a candidate function inside the tests: every call runs in C."""

    def __init__(self, link, name):
        self._link = link
        self.__name__ = self.__qualname__ = name

    def __call__(self, *args, **kwargs):
        return self._link.call(self.__name__, args, kwargs)

    def __repr__(self):
        return "<candidate %s>" % self.__name__


def format_exc():
    import traceback
    return traceback.format_exc()


def run(task, link, out):
    try:
        send(link.wfd, ("load", task["setup"], task["code"]))
        reply = link.receive()
    except Deadline:
        out["status"] = "timeout_load"
        return out
    except (Gone, OSError):
        link.mark_gone("the candidate process exited")
        out["status"] = "exited_load"
        return out
    except MemoryError:
        link.memory = True
        out["status"] = "load_error"
        return out
    # C's reply is untrusted (the candidate may have written into the pipe): check its shape.
    kind = reply[0] if isinstance(reply, tuple) and len(reply) >= 2 else None
    if kind == "syntax_error":
        out.update(status="syntax_error", message=str(reply[1]))
        return out
    if kind == "setup_error":
        out.update(status="reference_error", message="setup failed in the sandbox: " + str(reply[1]))
        return out
    if kind == "load_error" and len(reply) == 4:
        if reply[1] == "MemoryError":
            link.memory = True
        out.update(status="load_error", error_type=str(reply[1]), message=str(reply[2]), traceback=str(reply[3]))
        return out
    if kind != "loaded" or not isinstance(reply[1], list):
        out["status"] = "protocol_error"
        link.mark_gone("protocol violation")
        return out
    functions = [f for f in reply[1] if isinstance(f, str)]
    out["functions"] = functions[:50]

    ns = {"__name__": "tests", "__builtins__": builtins}
    for label, source in (("setup", task["setup"]), ("prompt", task["prompt"] or "")):
        # Reference code runs here, in P: helpers the tests use (HumanEval/32's poly) are
        # the reference's own, not whatever the candidate redefined them to.
        try:
            exec(compile(source, "<%s>" % label, "exec"), ns)
        except Exception:
            out.update(status="reference_error", message=label + " failed: " + format_exc()[-800:])
            return out
    if task["entry_point"]:
        ns[task["entry_point"]] = Candidate(link, task["entry_point"])  # replaces the prompt's stub
    for name in task["proxies"]:
        if name not in ns:
            ns[name] = Candidate(link, name)
    units = []
    if task["kind"] == "check":
        try:
            exec(compile(task["tests"], "<tests>", "exec"), ns)
        except (Deadline, Gone):
            raise
        except Exception:
            if link.seq == 0:
                out.update(status="reference_error", message="tests failed to load: " + format_exc()[-800:])
                return out
            out["failures"].append({"test": 0, "error": "the test module failed: " + format_exc()[-300:]})
            out["executed"] = out["total"]
            return out
        entry = task["entry_point"] or (functions[-1] if functions else None)
        if entry is None:
            out["failures"].append({"test": 0, "error": "the candidate defines no function"})
            out["executed"] = out["total"]
            return out
        check = ns.get("check")
        units.append(("check(%s)" % entry, lambda: check(Candidate(link, entry))))
    else:
        for source, runnable in task["tests"]:
            code = compile(runnable, "<test>", "exec")
            units.append((source, lambda code=code: exec(code, ns)))
    for index, (label, unit) in enumerate(units):
        if link.timeout or link.gone:
            why = "timeout" if link.timeout else link.gone
            if len(out["failures"]) < CFG["max_failures"]:
                out["failures"].append({"test": index, "error": "not run: " + why})
            continue
        out["executed"] += 1
        error = None
        try:
            unit()
        except Deadline:
            link.timeout = True
            error = "timeout"
        except Gone as exc:
            error = str(exc)
        except MemoryError:
            link.memory = True
            error = "MemoryError"
        except BaseException as exc:
            error = describe(exc)
            if task["kind"] == "check":
                error += test_line(exc, task["tests"])
        if error is None and (link.timeout or link.gone):
            error = "timeout" if link.timeout else link.gone  # swallowed by the test code
        if error is None:
            out["passed"] += 1
        elif len(out["failures"]) < CFG["max_failures"]:
            out["failures"].append({"test": index, "label": label[:200], "error": error})
    return out


def main():
    harden()
    c_in_r, p_out_w = os.pipe()  # P -> C
    p_in_r, c_out_w = os.pipe()  # C -> P
    pid = os.fork()  # before reading the task: C never holds the tests or the nonce
    if pid == 0:
        try:
            os.close(p_out_w)
            os.close(p_in_r)
            child_main(c_in_r, c_out_w)
        finally:
            os._exit(0)
    os.close(c_in_r)
    os.close(c_out_w)
    chunks = []
    while True:
        chunk = os.read(0, 1 << 16)
        if not chunk:
            break
        chunks.append(chunk)
    task = marshal.loads(b"".join(chunks))
    nonce = task.pop("nonce")

    def on_alarm(signum, frame):
        raise Deadline()

    link = Link(pid, p_out_w, p_in_r)
    out = {"status": "done", "total": task["n_tests"], "executed": 0, "passed": 0, "failures": []}
    # One-shot backstop for time spent in P itself (the tests' own code); the pipe reads
    # have their own deadline. The timer fires at most once, and every place it can fire
    # is inside this try, so partial counts in `out` survive.
    signal.signal(signal.SIGALRM, on_alarm)
    try:
        try:
            signal.setitimer(signal.ITIMER_REAL, max(DEADLINE - time.monotonic(), 0.001))
            run(task, link, out)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
    except Deadline:
        link.timeout = True
    except Gone:
        pass
    if link.timeout:
        out["timeout"] = True
    if link.memory:
        out["memory"] = True
    if link.gone:
        out["gone"] = link.gone
    if link.status is None:
        link.reap(0.0)
    if link.status is not None:
        st = link.status
        out["child"] = {"signal": os.WTERMSIG(st)} if os.WIFSIGNALED(st) else {"exit": os.WEXITSTATUS(st)}
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)  # reap C here: an orphaned zombie would count against the uid's RLIMIT_NPROC
    except OSError:
        pass
    out["nonce"] = nonce
    return out


try:
    RESULT = main()
except BaseException:
    signal.setitimer(signal.ITIMER_REAL, 0)
    RESULT = {"status": "harness_error", "message": format_exc()[-2000:]}
write_all(1, (repr(RESULT) + "\n").encode("utf-8", "backslashreplace"))
os._exit(0)
