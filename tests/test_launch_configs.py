"""The shipped accelerate launch configs (recipes/launch/*.yaml) parse with accelerate's own config
class and say how to run them. Only cpu-2proc.yaml runs here (tests/posttrain/test_distributed.py);
the GPU / FSDP / DeepSpeed ones cannot run on this CPU-only CI and are checked for shape only."""
from __future__ import annotations

from pathlib import Path

import pytest

LAUNCH = Path(__file__).resolve().parents[1] / "recipes" / "launch"
EXPECTED = {"cpu-2proc": "MULTI_GPU", "single-gpu": "NO", "multi-gpu-ddp": "MULTI_GPU", "fsdp": "FSDP",
            "deepspeed-zero2": "DEEPSPEED", "deepspeed-zero3": "DEEPSPEED"}


def test_every_expected_config_is_shipped():
    assert sorted(p.stem for p in LAUNCH.glob("*.yaml")) == sorted(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_config_parses_with_accelerate(name):
    from accelerate.commands.config.config_args import ClusterConfig

    path = LAUNCH / f"{name}.yaml"
    cfg = ClusterConfig.from_yaml_file(str(path))
    assert str(cfg.distributed_type).split(".")[-1] == EXPECTED[name]
    header = path.read_text().split("\ncompute_environment")[0]
    assert f"accelerate launch --config_file recipes/launch/{name}.yaml -m posttrain" in header
    if name.startswith("deepspeed"):
        assert cfg.deepspeed_config["zero_stage"] == int(name[-1])
        assert cfg.deepspeed_config["gradient_accumulation_steps"] == 1  # posttrain accumulates itself
    if name == "fsdp":
        assert cfg.fsdp_config["fsdp_transformer_layer_cls_to_wrap"] == "LlamaDecoderLayer"
        from transformers.models.llama.modeling_llama import LlamaDecoderLayer  # the class named exists

        assert LlamaDecoderLayer.__name__ == "LlamaDecoderLayer"
