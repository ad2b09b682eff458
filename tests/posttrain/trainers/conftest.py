"""Fixtures of the multi-turn trainer tests (test_grpo_env.py, test_ppo_env.py; test_distributed.py has its own)."""
import importlib.util
from pathlib import Path

import pytest

ENVS = Path(__file__).resolve().parent.parent / "envs_for_tests.py"


@pytest.fixture(scope="session")
def chat_sft(tiny_lm, tmp_path_factory):
    """The 'SFT model' the environment trainers start from: a random tiny model with a chat tokenizer trained on
    tiny-calc text, its eos made likely enough that some turns (not all) end early (envs_for_tests.eos_pulled_copy)."""
    spec = importlib.util.spec_from_file_location("envs_for_tests", ENVS)
    envs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(envs)
    src = tiny_lm("tiny-calc", vocab_size=320, max_length=256, split_digits=True, chat=True)
    return envs.eos_pulled_copy(src, tmp_path_factory.mktemp("chat-sft") / "model")

