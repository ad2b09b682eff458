"""posttrain: LLM post-training (SFT, reward models, DPO, PPO, GRPO, distillation) on a laptop CPU or GPUs.

This file imports nothing heavy (no torch), so `import posttrain.verifiers` (the verifier layer, shipped from the
repository's top-level `verifiers/` folder) stays torch-free.
"""
from __future__ import annotations


class _SourceCheckoutVerifiers:
    """A source checkout run without installing (`PYTHONPATH=<repo>`, as on a machine with no network): an install
    maps the repository's `verifiers/` folder to `posttrain.verifiers` (pyproject.toml's package-dir); here nothing
    does, so this finder maps that one name, and only when no installed copy answers for it (it runs last)."""

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name != __name__ + ".verifiers":
            return None
        import importlib.util
        from pathlib import Path

        src = Path(__file__).resolve().parent.parent / "verifiers"
        if not (src / "__init__.py").is_file():
            return None
        return importlib.util.spec_from_file_location(name, src / "__init__.py", submodule_search_locations=[str(src)])


def _install_finder() -> None:
    import sys

    if not any(f is _SourceCheckoutVerifiers or type(f).__name__ == "_SourceCheckoutVerifiers" for f in sys.meta_path):
        sys.meta_path.append(_SourceCheckoutVerifiers)


_install_finder()
