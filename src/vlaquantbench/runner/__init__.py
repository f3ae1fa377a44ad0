"""Closed-loop rollouts of one cell over batched simulator environments, crash-safe and resumable.

`runner.cell` runs one cell end to end, `runner.loop` is the batched closed loop, `runner.journal`
makes per-episode appends durable, `runner.checkpoint` fetches pinned checkpoints and
`runner.calibration` collects rollout calibration statistics. (Nothing is imported here, so the
workflow can read `runner.checkpoint` without loading torch.)
"""
