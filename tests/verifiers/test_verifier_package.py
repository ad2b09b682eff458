"""The verifier layer (posttrain.verifiers) imports and runs with torch and the rest of posttrain unavailable; sympy
loads only when needed."""
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

SCRIPT = r'''
import sys

class Block:
    """Make torch, transformers, numpy and every posttrain module outside posttrain.verifiers unimportable."""
    def find_spec(self, name, path=None, target=None):
        ours = name == "posttrain" or name == "posttrain.verifiers" or name.startswith("posttrain.verifiers.")
        if name.split(".")[0] in ("torch", "transformers", "numpy") or (name.startswith("posttrain") and not ours):
            raise ImportError(f"blocked: {name}")
        return None

sys.meta_path.insert(0, Block())
import posttrain.verifiers, posttrain.verifiers.registry, posttrain.verifiers.runner, posttrain.verifiers.audit, posttrain.verifiers.cli, posttrain.verifiers.format, posttrain.verifiers.combine
import posttrain.verifiers.math_answer
print("sympy-after-import", "sympy" in sys.modules)
from posttrain.verifiers import get_verifier, score_batch
v = get_verifier("0.9*math+0.1*format")
print("scores", [o.score for o in score_batch(v, [r"\boxed{x^2}", "1"], ["x**2", "2"], workers=1)])
print("sympy-after-use", "sympy" in sys.modules)
'''


def test_imports_without_torch_or_posttrain():
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines == ["sympy-after-import False", "scores [1.0, 0.0]", "sympy-after-use True"]
