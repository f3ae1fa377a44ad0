"""The workflow run that tests/test_demonstrations.py and tests/test_training.py both read (`demonstrations_run`
in conftest.py): rule demonstrations on two Meta-World tasks at 32 pixels, then rule train_policy on its dataset,
in one `snakemake` of a fresh working folder.

The failed demonstration is real: the step limit is 45, so reach-v3's expert fails on variation 500 (it needs 51
steps there, measured with metaworld 3.0.0) and succeeds on 501 (44 steps), while handle-press-v3 succeeds on 500
(32 steps)."""

TASKS = ["reach-v3", "handle-press-v3"]
EXPERTS = {"benchmark": "metaworld"}  # whose scripted experts are recorded
DEMONSTRATIONS = {**EXPERTS, "dir": "results/demos", "tasks": TASKS, "episodes_per_task": 1, "max_steps": 45,
                  "image_size": 32, "image_writer_threads": 1}
# A tiny pi0.5 (tests/test_training.py trains it in-process too): its images are 2 x 2 patches of 14 pixels (28 or
# 32 pixels a side), so the 27-layer vision tower stays cheap on a CPU.
TINY_POLICY = {
    "chunk_size": 4, "n_action_steps": 2, "tokenizer_max_length": 24,
    "normalization": {"VISUAL": "IDENTITY", "STATE": "MIN_MAX", "ACTION": "MEAN_STD"},
    "lr": 1e-3, "warmup_steps": 5, "decay_steps": 40, "decay_lr": 1e-4,
    "widths": {"vision": {"hidden_size": 16, "intermediate_size": 32, "num_attention_heads": 2},
               "gemma_2b": {"width": 32, "mlp_dim": 64, "head_dim": 4},
               "gemma_300m": {"width": 16, "mlp_dim": 32}},
}
TRAINING = {"model": "pi05", "output": "checkpoints/tiny", "checkpoint_repo": "vlaquantbench/pi05-tiny",
            "tokenizer_repo": "vlaquantbench/pi05-tiny-tokenizer", "device": "cpu", "seed": 0, "steps": 2,
            "batch_size": 4, "log_every": 1, "policy": TINY_POLICY}
TARGETS = ("results/demos/manifest.tsv", "checkpoints/tiny/training.json")
