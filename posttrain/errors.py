"""The errors a user can cause, one class per kind, each raised with one line naming the thing and the fix.

The bottom layer of the package: it imports nothing of posttrain, so every module can raise these.
The CLI (`posttrain.cli.main`) prints them as one line and exits non-zero; our own bugs raise anything else.
"""
from __future__ import annotations


class ConfigError(ValueError):
    """A user-caused config problem: one line naming the key and how to fix it."""


class DataError(ValueError):
    """A bad data file or row, in one line: ``<file>: row <N>: field '<name>': <problem>``."""


class ModelError(ValueError):
    """A model or tokenizer the user pointed at cannot be used (missing path, not a model dir)."""


class TrainingError(RuntimeError):
    """A run cannot go on (non-finite loss, ...); the last good checkpoint is intact."""
