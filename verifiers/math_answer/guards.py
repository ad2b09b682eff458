"""Hard limits on model output and the sympy call budget (policy: "Hard limits" and
"Equivalence" in the package docstring, verifiers/math_answer/__init__.py).

sympy itself is imported on first use (`_sp`), so numeric answers and `import verifiers` never load it.
"""
from __future__ import annotations

import sys
import threading

MAX_ANSWER_CHARS = 1000   # longest extracted answer we try to parse
MAX_DIGITS = 4000         # largest number we build (also below Python's int->str limit)
MAX_FACTORIAL = 3000
MAX_ITEMS = 64            # list / set / tuple elements
MAX_PM = 4                # \pm signs in one answer (2**4 alternatives)
DEFAULT_BUDGET = 1_000_000  # Python function calls for all sympy work on one completion

_sympy = None


def _sp():
    """sympy, imported on first use (numeric answers never need it)."""
    global _sympy
    if _sympy is None:
        import sympy

        _sympy = sympy
    return _sympy


class Unparseable(Exception):
    """The model's answer cannot be read (bad model output, never raised out of `check`)."""


class _BudgetExceeded(BaseException):
    """Raised from the call tracer; BaseException so sympy's `except Exception` cannot swallow it."""


_budget_state = threading.local()


class _CallBudget:
    """Limit the Python function calls made inside a block (deterministic, thread-local).

    Implemented with `sys.settrace`: the global trace function counts 'call' events and raises
    `_BudgetExceeded` past the limit. Works in any thread and in worker processes. It cannot
    interrupt a single long C call, which is why big numbers are refused before they are built.
    """

    def __init__(self, limit: int):
        self.limit = limit
        self.nested = False

    def __enter__(self) -> "_CallBudget":
        if getattr(_budget_state, "active", False):
            self.nested = True
            return self
        _budget_state.active = True
        self._old = sys.gettrace()
        count = 0
        limit = self.limit

        def tracer(frame, event, arg):
            nonlocal count
            count += 1
            if count > limit:
                raise _BudgetExceeded()
            return None

        sys.settrace(tracer)
        return self

    def __exit__(self, *exc) -> None:
        if self.nested:
            return
        sys.settrace(self._old)
        _budget_state.active = False
