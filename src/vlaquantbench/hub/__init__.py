"""Hugging Face hub artefacts: the offline cache fixture of the released checkpoints (`fixture`),
written in huggingface_hub's own cache layout (`cache`), and the checks a loaded snapshot must pass
before any rollout (`checks`)."""
