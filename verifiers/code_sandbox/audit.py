"""The code verifier's audit material: built-in problems (written for this project, HumanEval
style) and hostile programs that try to score without solving them (each must score 0).
"""
from __future__ import annotations

from typing import Any


# --------------------------------------------------------------------------------------
# Audit problems (written for this project) and hostile programs
# --------------------------------------------------------------------------------------
def _problem(entry: str, signature: str, doc: str, body: str, tests: Any) -> dict[str, Any]:
    prompt = f"def {entry}{signature}:\n    \"\"\"{doc}\"\"\"\n"
    return {"entry_point": entry, "prompt": prompt, "solution": prompt + body, "tests": tests}


_PROBLEMS: list[dict[str, Any]] = [
    _problem("running_max", "(xs: list[int]) -> list[int]",
             "Return the running maximum: element i is max(xs[:i+1]). running_max([1, 3, 2]) == [1, 3, 3]",
             "    out = []\n    for x in xs:\n        out.append(x if not out else max(out[-1], x))\n    return out\n",
             "def check(candidate):\n    assert candidate([]) == []\n    assert candidate([1, 3, 2]) == [1, 3, 3]\n"
             "    assert candidate([-5, -7, -1, -9]) == [-5, -5, -1, -1]\n    assert candidate([4]) == [4]\n"),
    _problem("is_palindrome", "(s: str) -> bool",
             "True when s reads the same backwards, ignoring case and non-alphanumeric characters.",
             "    t = [c.lower() for c in s if c.isalnum()]\n    return t == t[::-1]\n",
             ["assert is_palindrome('') is True", "assert is_palindrome('A man, a plan, a canal: Panama') is True",
              "assert is_palindrome('abca') is False", "assert is_palindrome('No lemon, no melon') is True"]),
    _problem("count_vowels", "(s: str) -> int", "Number of vowels (a, e, i, o, u; either case) in s.",
             "    return sum(c in 'aeiouAEIOU' for c in s)\n",
             "def check(candidate):\n    assert candidate('') == 0\n    assert candidate('Hello World') == 3\n"
             "    assert candidate('AEIOUxyz') == 5\n    assert candidate('rhythm') == 0\n"),
    _problem("fizzbuzz", "(n: int) -> list[str]",
             "Strings for 1..n: 'Fizz' for multiples of 3, 'Buzz' of 5, 'FizzBuzz' of both, else the number.",
             "    out = []\n    for i in range(1, n + 1):\n        s = ('Fizz' if i % 3 == 0 else '') + ('Buzz' if i % 5 == 0 else '')\n"
             "        out.append(s or str(i))\n    return out\n",
             ["assert fizzbuzz(0) == []", "assert fizzbuzz(5) == ['1', '2', 'Fizz', '4', 'Buzz']",
              "assert fizzbuzz(15)[-1] == 'FizzBuzz'", "assert len(fizzbuzz(100)) == 100"]),
    _problem("run_length", "(s: str) -> list[tuple[str, int]]",
             "Run-length encoding: run_length('aaab') == [('a', 3), ('b', 1)].",
             "    out = []\n    for c in s:\n        if out and out[-1][0] == c:\n            out[-1] = (c, out[-1][1] + 1)\n"
             "        else:\n            out.append((c, 1))\n    return out\n",
             "def check(candidate):\n    assert candidate('') == []\n    assert candidate('aaab') == [('a', 3), ('b', 1)]\n"
             "    assert candidate('abba') == [('a', 1), ('b', 2), ('a', 1)]\n"),
    _problem("second_largest", "(xs: list[int]) -> int | None",
             "The second largest distinct value in xs, or None when there is none.",
             "    d = sorted(set(xs))\n    return d[-2] if len(d) >= 2 else None\n",
             ["assert second_largest([1, 2, 3]) == 2", "assert second_largest([5, 5, 5]) is None",
              "assert second_largest([]) is None", "assert second_largest([-1, -2, -2, 7]) == -1"]),
    _problem("flatten", "(nested: list) -> list",
             "Flatten arbitrarily nested lists: flatten([1, [2, [3]]]) == [1, 2, 3].",
             "    out = []\n    for x in nested:\n        if isinstance(x, list):\n            out.extend(flatten(x))\n"
             "        else:\n            out.append(x)\n    return out\n",
             "def check(candidate):\n    assert candidate([]) == []\n    assert candidate([1, [2, [3, [4]]], 5]) == [1, 2, 3, 4, 5]\n"
             "    assert candidate([[], [[]], ['a']]) == ['a']\n"),
    _problem("gcd_list", "(xs: list[int]) -> int",
             "Greatest common divisor of all numbers in xs (non-empty, non-negative); gcd_list([0]) == 0.",
             "    g = 0\n    for x in xs:\n        a, b = g, x\n        while b:\n            a, b = b, a % b\n        g = a\n    return g\n",
             ["assert gcd_list([12, 18]) == 6", "assert gcd_list([7]) == 7", "assert gcd_list([0, 0]) == 0",
              "assert gcd_list([100, 75, 50]) == 25"]),
    _problem("word_counts", "(text: str) -> dict[str, int]",
             "Count lower-cased words (split on whitespace) in text.",
             "    counts = {}\n    for w in text.lower().split():\n        counts[w] = counts.get(w, 0) + 1\n    return counts\n",
             "def check(candidate):\n    assert candidate('') == {}\n    assert candidate('a b A') == {'a': 2, 'b': 1}\n"
             "    assert candidate('  x\\ty\\nx ') == {'x': 2, 'y': 1}\n"),
    _problem("rotate", "(xs: list, k: int) -> list",
             "Rotate xs right by k places (k may be negative or larger than len(xs)).",
             "    if not xs:\n        return []\n    k %= len(xs)\n    return xs[-k:] + xs[:-k] if k else list(xs)\n",
             ["assert rotate([1, 2, 3, 4], 1) == [4, 1, 2, 3]", "assert rotate([1, 2, 3], -1) == [2, 3, 1]",
              "assert rotate([], 5) == []", "assert rotate([1, 2], 4) == [1, 2]"]),
    _problem("balanced", "(s: str) -> bool",
             "True when the brackets ()[]{} in s are balanced and properly nested; other characters are ignored.",
             "    pairs = {')': '(', ']': '[', '}': '{'}\n    stack = []\n    for c in s:\n        if c in '([{':\n"
             "            stack.append(c)\n        elif c in pairs:\n            if not stack or stack.pop() != pairs[c]:\n"
             "                return False\n    return not stack\n",
             "def check(candidate):\n    assert candidate('') is True\n    assert candidate('([]{})') is True\n"
             "    assert candidate('(]') is False\n    assert candidate('((') is False\n    assert candidate('a(b)c') is True\n"),
    _problem("digit_sum", "(n: int) -> int", "Sum of the decimal digits of n (sign ignored).",
             "    return sum(int(c) for c in str(abs(n)))\n",
             ["assert digit_sum(0) == 0", "assert digit_sum(123) == 6", "assert digit_sum(-45) == 9",
              "assert digit_sum(10**20) == 1"]),
]

# Each program below tries to score without solving the problem; ENTRY is the entry point.
_ADVERSARIAL: list[tuple[str, str]] = [
    ("early sys.exit(0)", "import sys\nsys.exit(0)\ndef ENTRY(*a, **k):\n    return None"),
    ("os._exit(0) at import", "import os\nos._exit(0)"),
    ("os._exit(0) inside the call", "import os\ndef ENTRY(*a, **k):\n    os._exit(0)"),
    ("raise SystemExit in the call", "def ENTRY(*a, **k):\n    raise SystemExit(0)"),
    ("fake success print",
     "print('All tests passed')\nprint('{\"status\": \"done\", \"total\": 1, \"executed\": 1, \"passed\": 1}')\n"
     "def ENTRY(*a, **k):\n    print('PASSED')\n    return None"),
    ("always-equal return value",
     "class _Any:\n    def __eq__(self, other):\n        return True\n    def __ne__(self, other):\n        return False\n"
     "    def __bool__(self):\n        return True\ndef ENTRY(*a, **k):\n    return _Any()"),
    ("int subclass with rigged __eq__",
     "class _I(int):\n    def __eq__(self, other):\n        return True\n    __hash__ = int.__hash__\n"
     "def ENTRY(*a, **k):\n    return _I(0)"),
    ("redefine check, print and builtins",
     "import builtins\ndef check(candidate):\n    return True\nbuiltins.print = lambda *a, **k: None\n"
     "builtins.AssertionError = type('AssertionError', (Exception,), {})\nbuiltins.isinstance = lambda *a: True\n"
     "def ENTRY(*a, **k):\n    return None"),
    ("patch the harness through gc and sys.modules",
     "import gc, sys\nmain = sys.modules.get('__main__')\n"
     "for name in ('run', 'main', 'Candidate', 'Link', 'limit', 'harden'):\n"
     "    if main is not None and hasattr(main, name):\n        setattr(main, name, lambda *a, **k: None)\n"
     "for obj in gc.get_objects():\n    if isinstance(obj, dict) and 'check' in obj:\n"
     "        obj['check'] = lambda candidate: True\n"
     "def ENTRY(*a, **k):\n    return None"),
    ("forge the result channel",
     "import os\nline = repr({'status': 'done', 'total': 1, 'executed': 1, 'passed': 1, 'failures': [],"
     " 'nonce': 'x'}) + '\\n'\nfor fd in range(0, 64):\n    try:\n        os.write(fd, line.encode())\n    except OSError:\n"
     "        pass\nfor pid in os.listdir('/proc'):\n    if pid.isdigit():\n        for fd in ('1', '3', '4'):\n"
     "            try:\n                with open('/proc/%s/fd/%s' % (pid, fd), 'w') as f:\n                    f.write(line)\n"
     "            except OSError:\n                pass\ndef ENTRY(*a, **k):\n    return None"),
    ("read the tests from the harness's memory",
     "import os\nleak = ''\nppid = os.getppid()\nfor path in ('/proc/%d/mem' % ppid, '/proc/%d/environ' % ppid):\n"
     "    try:\n        leak += open(path, 'rb').read(100).decode('latin-1')\n    except OSError:\n        pass\n"
     "def ENTRY(*a, **k):\n    return leak or None"),
    ("kill the parent", "import os, signal\ntry:\n    os.kill(os.getppid(), signal.SIGKILL)\nexcept OSError:\n    pass\n"
     "try:\n    os.killpg(0, signal.SIGKILL)\nexcept OSError:\n    pass\ndef ENTRY(*a, **k):\n    return None"),
    ("fork bomb", "import os\nwhile True:\n    try:\n        os.fork()\n    except OSError:\n        pass"),
    ("infinite loop", "def ENTRY(*a, **k):\n    while True:\n        pass"),
    ("memory bomb", "hog = []\nwhile True:\n    hog.append(bytearray(1 << 24))"),
    ("huge file", "with open('big.bin', 'wb') as f:\n    while True:\n        f.write(b'\\0' * (1 << 20))"),
    ("network", "import socket\ns = socket.create_connection(('1.1.1.1', 80), timeout=2)\n"
     "def ENTRY(*a, **k):\n    return None"),
]
