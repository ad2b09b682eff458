"""Tests for posttrain.verifiers.envs.tools: the exact calculator, the seeded fact table and the sandboxed Python
tool (formats, limits, error messages, determinism, containment)."""
from __future__ import annotations

import os
import random
import re
import subprocess
import sys
import time
import uuid
from fractions import Fraction

import pytest

from posttrain.verifiers.envs.tools import FACT_ATTRIBUTES, FactTable, PythonTool, calculator

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


# --------------------------------------------------------------------------------------
# Calculator
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("expression, expected", [
    ("123*456", "56088"),
    ("(2+3)*4-5/2", "17.5"),
    ("1/3", "1/3 (≈ 0.333333333333)"),
    ("-7/3", "-7/3 (≈ -2.33333333333)"),
    ("2**100", str(2 ** 100)),
    ("2**-3", "0.125"),
    ("-1/8", "-0.125"),
    ("10//3", "3"),
    ("-10//3", "-4"),
    ("10%3", "1"),
    ("-10%3", "2"),
    ("-(-2)", "2"),
    ("--2", "2"),
    ("-2**2", "-4"),
    ("2**3**2", "512"),
    ("(-2)**3", "-8"),
    (".5 + 5.", "5.5"),
    ("0.1+0.2", "0.3"),
    ("  1 +\t2\n", "3"),
    ("6/4*2", "3"),
    ("9999*9999*9999*9999", str(9999 ** 4)),
    ("4821*7730-1234*5678", str(4821 * 7730 - 1234 * 5678)),
    ("1/7", "1/7 (≈ 0.142857142857)"),
    ("1/3000000000", "1/3000000000 (≈ 3.33333333333E-10)"),
    ("10/4//1", "2"),  # integer-valued operands only, and 10/4 is 2.5 -> 2.5//1 is an error; see below
])
def test_calculator_exact_values(expression, expected):
    if expression == "10/4//1":
        with pytest.raises(ValueError, match="whole-number operands at character 5"):
            calculator(expression)
        return
    assert calculator(expression) == expected


@pytest.mark.parametrize("expression, message", [
    ("", "empty expression"),
    ("   ", "empty expression"),
    ("2+", "unexpected end of expression at character 3"),
    ("2**1000", "exponent too large at character 2"),
    ("10**64*10**64*10**64*10**64", "result too large"),
    ("__import__('os')", "unexpected character '_' at character 1"),
    ("1e9999", "unexpected character 'e' at character 2 (no exponent notation)"),
    ("2 2", "unexpected number '2' at character 3"),
    ("(1+2))", "unexpected ')' at character 6"),
    ("(1+2", "missing ')' for the '(' at character 1"),
    ("()", "unexpected ')' at character 2"),
    ("*3", "unexpected '*' at character 1"),
    ("1/0", "division by zero at character 2"),
    ("5%(3-3)", "division by zero at character 2"),
    ("7//0", "division by zero at character 2"),
    ("0**-1", "division by zero at character 2"),
    ("1.5%1", "'%' needs whole-number operands at character 4"),
    ("2**0.5", "'**' needs a whole-number exponent at character 2"),
    ("3×4", "unexpected character '×' at character 2 (use * for multiplication)"),
    ("3x4", "use * for multiplication"),
    ("8÷2", "use / for division"),
    ("2^3", "use ** for powers"),
    ("−2", "use - for minus"),
    ("1,000", "no thousands separators"),
    ("1..2", "invalid number '1..2' at character 1"),
    (".", "invalid number '.' at character 1"),
    ("9" * 31, "number too long at character 1 (at most 30 digits)"),
    ("1" * 201, "expression too long (201 characters; at most 200)"),
    ("٣+1", "unexpected character '٣' at character 1"),  # non-ASCII digits are not numbers
    ("abs(-1)", "unexpected character 'a' at character 1"),
])
def test_calculator_errors_name_the_problem(expression, message):
    with pytest.raises(ValueError) as info:
        calculator(expression)
    assert message in str(info.value)


def test_calculator_nesting_limit():
    assert calculator("(" * 32 + "1" + ")" * 32) == "1"
    with pytest.raises(ValueError, match="parentheses nested too deep at character 33"):
        calculator("(" * 33 + "1" + ")" * 33)
    assert calculator("-" * 150 + "1") == "1"  # a long unary chain is a loop, not recursion


def test_calculator_limits_on_sizes():
    assert calculator("9" * 30 + "+1") == "1" + "0" * 30
    assert calculator("10**199") == "1" + "0" * 199  # 200 digits: allowed
    with pytest.raises(ValueError, match="result too large"):
        calculator("10**200")
    with pytest.raises(ValueError, match="result too large"):
        calculator("1/10**200")
    with pytest.raises(ValueError, match="result too large"):  # an intermediate value, not only the result
        calculator("10**100*10**100-10**100*10**100")


def test_calculator_rejects_non_strings():
    with pytest.raises(TypeError, match="expression must be a string, got int"):
        calculator(12)  # type: ignore[arg-type]


def test_calculator_messages_are_one_line():
    for bad in ["", "2+", "(", "1/0", "x", "2**999", "1" * 300]:
        with pytest.raises(ValueError) as info:
            calculator(bad)
        assert "\n" not in str(info.value) and len(str(info.value)) < 120


def _random_expression(rng: random.Random, depth: int) -> str:
    """A random expression string in the calculator's grammar, parenthesised at random."""
    if depth == 0 or rng.random() < 0.3:
        kind = rng.random()
        if kind < 0.6:
            return str(rng.randint(0, 9999))
        if kind < 0.8:
            return f"{rng.randint(0, 99)}.{rng.randint(0, 99):02d}"
        return str(rng.randint(0, 9))
    op = rng.choice(["+", "-", "*", "/", "//", "%", "**", "u-", "+", "*"])
    if op == "u-":
        return "-" + _random_expression(rng, depth - 1)
    left = _random_expression(rng, depth - 1)
    right = str(rng.randint(-2, 3)) if op == "**" else _random_expression(rng, depth - 1)
    if op == "**" and right.startswith("-"):
        right = f"({right})" if rng.random() < 0.5 else right
    text = f"{left}{rng.choice(['', ' '])}{op}{rng.choice(['', ' '])}{right}"
    return f"({text})" if rng.random() < 0.6 else text


def _python_value(expression: str) -> Fraction:
    """The same expression under Python's own grammar, with every number an exact Fraction."""
    source = re.sub(r"(\d+\.?\d*|\.\d+)", r"F('\1')", expression)
    value = eval(source, {"F": Fraction, "__builtins__": {}})  # the TEST's oracle; the module never evaluates
    return Fraction(value)


def _parse_output(text: str) -> Fraction:
    match = re.fullmatch(r"(-?\d+)/(\d+) \(≈ (-?[\d.E+-]+)\)", text)
    if match:
        value = Fraction(int(match[1]), int(match[2]))
        assert value.denominator == int(match[2]) > 1  # reduced, not an integer
        d = value.denominator
        while d % 2 == 0:
            d //= 2
        while d % 5 == 0:
            d //= 5
        assert d != 1, f"{text}: a finite decimal should be written as one"
        assert abs(Fraction(match[3]) - value) <= abs(value) * Fraction(1, 10 ** 11)
        return value
    assert re.fullmatch(r"-?\d+(\.\d*[1-9])?", text), text  # digits, or an exact decimal without trailing zeros
    return Fraction(text)


DOCUMENTED_ERRORS = (r"('//'|'%') needs whole-number operands|'\*\*' needs a whole-number exponent|exponent too large|"
                     r"result too large|division by zero")


def test_calculator_matches_python_fraction_arithmetic():
    """Seeded random expressions: the calculator's value equals Python's (same precedence), or it raises one of its
    documented errors (division by zero only where Python divides by zero too)."""
    rng = random.Random(1234)
    compared = 0
    for _ in range(1500):
        expression = _random_expression(rng, rng.randint(1, 5))
        if len(expression) > 200:
            continue
        try:
            expected: Fraction | None = _python_value(expression)
            python_error = None
        except (ZeroDivisionError, TypeError, ValueError, OverflowError) as exc:  # e.g. (-8)**(1/2) is complex
            expected, python_error = None, exc
        try:
            got = calculator(expression)
        except ValueError as exc:
            message = str(exc)
            assert re.match(DOCUMENTED_ERRORS, message), (expression, message)
            if message.startswith("division by zero"):  # same values in the same order, so Python divides by 0 too
                assert isinstance(python_error, ZeroDivisionError), (expression, message)
            continue
        assert python_error is None, (expression, got)
        assert _parse_output(got) == expected, (expression, got, expected)
        compared += 1
    assert compared > 700  # most expressions are valid, so the comparison is not vacuous


# --------------------------------------------------------------------------------------
# Fact table
# --------------------------------------------------------------------------------------
def test_fact_table_golden_values():
    """Pins the generator: a change here changes every lookup environment's problems."""
    table = FactTable(seed=0, size=200)
    assert table.entries()[0] == {"name": "Zapeivum", "population": 751083, "founded": 1806, "height_m": 3654,
                                  "distance_km": 3583}
    assert table.names()[:5] == ["Zapeivum", "Rigu", "Dretousom", "Foubeil", "Shonim"]


def test_fact_table_is_deterministic_across_processes():
    script = "from posttrain.verifiers.envs.tools import FactTable; print(FactTable(seed=7, size=50).entries())"
    outputs = set()
    for hash_seed in ("1", "2"):
        env = dict(os.environ, PYTHONHASHSEED=hash_seed)
        proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, env=env, capture_output=True, text=True,
                              timeout=60)
        assert proc.returncode == 0, proc.stderr
        outputs.add(proc.stdout)
    assert outputs == {str(FactTable(seed=7, size=50).entries()) + "\n"}
    assert FactTable(seed=8, size=50).entries() != FactTable(seed=7, size=50).entries()


def test_fact_table_names_unique_and_values_in_range():
    table = FactTable(seed=3, size=2000)
    names = table.names()
    assert len(table) == len(names) == 2000
    assert len({n.casefold() for n in names}) == 2000
    for entry in table.entries():
        assert re.fullmatch(r"[A-Z][a-z]{3,}", str(entry["name"]))
        assert set(entry) == {"name", *FACT_ATTRIBUTES}
        assert all(isinstance(entry[a], int) for a in FACT_ATTRIBUTES)
        assert 612 <= int(entry["founded"]) <= 1987


def test_fact_table_lookup_matching_and_errors():
    table = FactTable(seed=0, size=50)
    name = table.names()[3]
    value = table.fact(name, "population")
    assert table.lookup(name, "population") == str(value)
    assert table.lookup(f"  {name.upper()} ", " Population ") == str(value)
    with pytest.raises(ValueError) as info:
        table.lookup(name[:-1], "population")  # a near miss: no suggestion that would leak an entry
    assert str(info.value) == f"no entry named {name[:-1]!r}"
    assert not any(n in str(info.value) for n in table.names())
    with pytest.raises(ValueError, match="unknown attribute 'age'; valid attributes: population, founded, height_m, "
                                         "distance_km"):
        table.lookup(name, "age")
    with pytest.raises(ValueError, match=r"no entry named 'x{37}\.\.\.'"):
        table.lookup("x" * 500, "founded")  # the echo is bounded
    with pytest.raises(TypeError):
        table.lookup(name, 3)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="FactTable seed must be an integer"):
        FactTable(seed="0")  # type: ignore[arg-type]
    for bad in (0, 10_001, 2.5):
        with pytest.raises(ValueError, match="FactTable size"):
            FactTable(size=bad)  # type: ignore[arg-type]


def test_fact_table_as_tool():
    table = FactTable(seed=1, size=20)
    lookup = table.as_tool()
    name = table.names()[0]
    assert lookup.__name__ == "lookup"
    assert lookup(name, "founded") == str(table.fact(name, "founded"))


# --------------------------------------------------------------------------------------
# Schemas
# --------------------------------------------------------------------------------------
def test_every_tool_has_a_json_schema():
    transformers_utils = pytest.importorskip("transformers.utils")
    tools = {"calculator": (calculator, ["expression"]), "lookup": (FactTable(size=5).as_tool(), ["name", "attribute"]),
             "python": (PythonTool().as_tool(), ["code"])}
    for name, (fn, params) in tools.items():
        schema = transformers_utils.get_json_schema(fn)
        function = schema["function"]
        assert function["name"] == name
        assert function["description"]
        assert list(function["parameters"]["properties"]) == params
        assert function["parameters"]["required"] == params
        for spec in function["parameters"]["properties"].values():
            assert spec["type"] == "string" and spec["description"]


# --------------------------------------------------------------------------------------
# Python tool (runs the code sandbox; each call is one sandbox start, about 0.1 s)
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def python_tool():
    return PythonTool(timeout_s=1.0, memory_mb=256, max_output_chars=200)


def test_python_prints(python_tool):
    run = python_tool.as_tool()
    assert run("print(sum(range(10)))\nprint('two')") == "45\ntwo\n"
    assert run("") == "(no output)"
    assert run("x = 1") == "(no output)"
    assert run("import sys\nprint('out')\nprint('warn', file=sys.stderr)") == "stdout:\nout\nstderr:\nwarn\n"
    # nothing in the code changes how the sandbox extracts the wrapper
    assert run("print('é ü ✓ </think> ```')") == "é ü ✓ </think> ```\n"
    assert run("print(__name__)") == "__main__\n"


def test_python_exception_traceback_tail(python_tool):
    out = python_tool.run("def f(x):\n    return 1 / x\n\nprint('before')\nf(0)\n")
    assert out.startswith("stdout:\nbefore\nstderr:\nTraceback (most recent call last):\n")
    assert 'File "<code>", line 5, in <module>' in out and "return 1 / x" in out  # the model's own lines
    assert "_posttrain" not in out and "<candidate>" not in out  # no wrapper frames
    assert out.endswith("ZeroDivisionError: division by zero\nexit status: 1")
    deep = python_tool.run("def f(n):\n    return f(n + 1)\nf(0)")
    assert deep.startswith("stderr:\n...[truncated ")  # stderr keeps its tail, where the exception is
    assert deep.endswith("RecursionError: maximum recursion depth exceeded\nexit status: 1")
    syntax = python_tool.run("def f(:\n    pass")
    assert "SyntaxError" in syntax and syntax.endswith("exit status: 1")


def test_python_exit_status(python_tool):
    assert python_tool.run("import sys; sys.exit(3)") == "exit status: 3"
    assert python_tool.run("import sys; sys.exit(0)") == "(no output)"
    assert python_tool.run("import sys; sys.exit('bye')") == "stderr:\nbye\nexit status: 1"
    assert python_tool.run("import os; os._exit(4)").startswith("error: the program was stopped (exited early")


def test_python_output_truncation(python_tool):
    out = python_tool.run("print('x' * 1000)")
    assert out == "x" * 200 + "\n...[truncated 801 characters]"
    err = python_tool.run("import sys\nfor i in range(500): print(i, file=sys.stderr)")
    assert err.startswith("stderr:\n...[truncated ") and err.endswith("499\n")
    assert len(err) < 260


def test_python_bypassing_sys_stdout_is_shown(python_tool):
    out = python_tool.run("import os\nos.write(1, b'direct\\n')\nprint('printed')")
    assert out == "stdout:\nprinted\nstderr:\ndirect\n"


def test_python_infinite_loop_times_out(python_tool):
    t0 = time.monotonic()
    out = python_tool.run("n = 0\nwhile True:\n    n += 1\n")
    assert out == "timeout: stopped after 1 s"
    assert time.monotonic() - t0 < 1.0 + 2.5
    # Code that swallows the soft deadline is stopped by the sandbox's own (1 s later); its output is lost.
    t0 = time.monotonic()
    out = python_tool.run("print('start')\nwhile True:\n    try:\n        while True:\n            x = 1\n"
                          "    except BaseException:\n        pass\n")
    assert out == "timeout: stopped after 1 s"
    assert time.monotonic() - t0 < 1.0 + 1.0 + 2.0 + 2.5


def test_python_output_before_a_timeout_comes_back(python_tool):
    out = python_tool.run("print('partial', flush=True)\nn = 0\nwhile True:\n    n += 1\n")
    assert out == "stdout:\npartial\ntimeout: stopped after 1 s"


def test_python_memory_limit(python_tool):
    out = python_tool.run("x = bytearray(2 * 1024 ** 3)")
    assert out.endswith("MemoryError\nexit status: 1")


def test_python_touches_no_host_files(python_tool, tmp_path):
    if python_tool.sandbox == "fallback (no namespaces)":
        pytest.skip("without namespaces the sandbox runs with rlimits only (see the code sandbox's threat model)")
    host_file = tmp_path / "written-by-the-tool.txt"
    top_tmp = f"/tmp/posttrain-tool-probe-{uuid.uuid4().hex}"
    out = python_tool.run(
        "import os\n"
        f"for path in ({str(host_file)!r}, {top_tmp!r}, 'here.txt'):\n"
        "    try:\n"
        "        open(path, 'w').write('x')\n"
        "        print('wrote', path)\n"
        "    except OSError as exc:\n"
        "        print('refused', path, type(exc).__name__)\n"
        "print(os.getcwd())\n")
    assert f"refused {host_file}" in out  # the checkout's and the host's paths are not even visible
    assert not host_file.exists() and not os.path.exists(top_tmp)
    assert not os.path.exists(os.path.join(REPO, "here.txt"))


def test_python_rejects_bad_input(python_tool):
    with pytest.raises(TypeError, match="code must be a string"):
        python_tool.run(None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="code too long"):
        PythonTool(max_code_chars=10).run("print('hello world')")
    with pytest.raises(ValueError, match="PythonTool limits"):
        PythonTool(timeout_s=0)
