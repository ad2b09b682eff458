"""The fast Llama-family forwards: the rollout engine's decoder (`decode`), the differentiable training
forward (`train`) and ONE check of what they can run (`support.lean_support`), which every caller asks
first; anything it refuses runs the model's own Hugging Face forward, with the same numbers."""
