"""Simulated benchmarks, one folder each (`envs/libero/`).

`BENCHMARK_SUITES` names every benchmark and its suites without importing a simulator, so cell
references are checked while the workflow builds the DAG.
"""

BENCHMARK_SUITES = {"libero": ("libero_spatial", "libero_object", "libero_goal", "libero_10")}
