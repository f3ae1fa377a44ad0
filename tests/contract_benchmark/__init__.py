"""A third benchmark that lives only under tests/ (issue 50, the seam's contract): a point-mass "hand" in a
MuJoCo scene this package writes itself, reaching a goal placed by the episode's seeded variation.

It follows the protocol `envs/metaworld/` implements (docs/simulators.md: adding a benchmark): a declaration
(`benchmark.py`) that registers itself, a suite (`suite.py`, a `SuiteTasks`), a vector env (`vector_env.py`, a
`WorkerVectorEnv`) and its worker (`worker.py`, `envs.workers.serve`). Nothing under src/ names it: processes find
it through `VQB_BENCHMARKS=contract_benchmark.benchmark` with tests/ on PYTHONPATH.

Its observation's `environment_state` has the layout of Meta-World's 39-dim observation (hand xyz, gripper,
object slots, the previous frame, goal xyz), so Meta-World's scripted reach experts (the `metaworld_expert`
model, tasks `reach-v3` and `reach-wall-v3`) can drive it without a network: a policy the runner already takes.
"""
