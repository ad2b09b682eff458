"""final/README.md is a Hugging Face model card: metadata the hub reads, the command, the run's evaluation, the
resolved config and the versions; the directory still loads with transformers; data outputs get no card."""
import json
import shutil

from posttrain import model_card
from posttrain.config import resolve
from posttrain.trainers.grpo import GRPOConfig


def test_a_model_card_with_metadata_command_evaluation_and_config(tiny_lm, tmp_path):
    from huggingface_hub import ModelCard
    from transformers import AutoModelForCausalLM

    final = tmp_path / "grpo" / "final"
    shutil.copytree(tiny_lm("tiny-countdown", vocab_size=256, max_length=128, split_digits=True), final)
    (final.parent / "eval.json").write_text(json.dumps({"model": str(final), "rows": 200,
                                                        "sft": {"eval/accuracy": 0.62}, "grpo": {"eval/accuracy": 0.95},
                                                        "samples": [{"prompt": "p", "completion": "c"}]}))
    res = resolve("tiny-math", "grpo", GRPOConfig, ["lr=2e-5"])
    path = model_card.write_card(final, res.to_dict(), ["posttrain", "grpo", "--recipe", "tiny-math", "lr=2e-5"])
    card = ModelCard.load(path)
    meta = card.data.to_dict()
    assert meta["library_name"] == "transformers" and meta["pipeline_tag"] == "text-generation"
    assert set(meta["tags"]) == {"posttrain", "grpo", "tiny-math"} and "base_model" not in meta  # a preset: no hub id
    text = card.text
    assert "posttrain grpo --recipe tiny-math lr=2e-5" in text and "a `tiny` preset built from scratch" in text
    assert "| grpo.eval/accuracy | 0.95 |" in text and "| sft.eval/accuracy | 0.62 |" in text
    assert "lr: 2.0e-05" in text and "transformers " in text and "samples" not in text.split("## Resolved")[0]
    assert AutoModelForCausalLM.from_pretrained(final).config.vocab_size > 0  # README.md changes nothing there
    assert model_card.write_card(tmp_path, res.to_dict(), ["posttrain"]) is None  # no config.json: not a model


def test_a_hub_id_base_model_is_named_in_the_metadata():
    base_id, words = model_card._origin({"model": {"path": "HuggingFaceTB/SmolLM2-135M-Instruct"}})
    assert base_id == "HuggingFaceTB/SmolLM2-135M-Instruct" and "SmolLM2" in words
    assert model_card._origin({"model": {"path": "/models/smol"}})[0] is None
