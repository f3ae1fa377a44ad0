"""`gpu_closed_loop.py` with the workers' time split by what they do, per measured run.

    MUJOCO_GL=egl python benchmarks/worker_time/closed_loop.py --num-envs 32 --bound-after 32 \\
        --out benchmarks/results/closed_loop_gpu_32_worker_time.json

Takes gpu_closed_loop.py's arguments; its workers run with `sitecustomize.py` (this folder) timing
their calls. Each run in the output gains `span` (perf_counter at its start and end) and
`worker_time`: per kind of call (`sitecustomize.KINDS`) the calls, mean wall and thread-CPU ms, the
90th percentile and largest wall ms, and wall and CPU seconds per worker, counting the calls that
began inside the run.
"""

import importlib.util
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import gpu_closed_loop  # noqa: E402


def _hooks():
    """This folder's sitecustomize as a module of its own name (another sitecustomize may be loaded);
    before WORKER_TIME_DIR is set, so that this process times nothing."""
    spec = importlib.util.spec_from_file_location("worker_time_hooks", HERE / "sitecustomize.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


KINDS = _hooks().KINDS


def worker_time(records: np.ndarray, span: list[float], num_envs: int) -> dict:
    inside = records[(records[:, 1] >= span[0]) & (records[:, 1] < span[1])]
    summary = {}
    for kind, name in enumerate(KINDS):
        calls = inside[inside[:, 0] == kind]
        if len(calls):
            wall, cpu = 1e3 * calls[:, 2], 1e3 * calls[:, 3]
            summary[name] = {"calls": len(calls), "wall_ms": round(float(wall.mean()), 2), "cpu_ms": round(float(cpu.mean()), 2),
                             "p90_wall_ms": round(float(np.percentile(wall, 90)), 2), "max_wall_ms": round(float(wall.max()), 1),
                             "wall_s_per_worker": round(float(wall.sum()) / 1e3 / num_envs, 2),
                             "cpu_s_per_worker": round(float(cpu.sum()) / 1e3 / num_envs, 2)}
    return summary


def main() -> None:
    directory = tempfile.mkdtemp(prefix="worker_time_")
    os.environ["WORKER_TIME_DIR"] = directory
    os.environ["PYTHONPATH"] = os.pathsep.join([str(HERE), *filter(None, [os.environ.get("PYTHONPATH")])])
    measure = gpu_closed_loop.measure

    def spanned(*args, **kwargs):
        began = time.perf_counter()
        result = measure(*args, **kwargs)
        result["span"] = [began, time.perf_counter()]
        return result

    gpu_closed_loop.measure = spanned
    out = gpu_closed_loop.main()  # every worker has exited (and dumped) when it returns
    result = json.loads(out.read_text())
    records = np.concatenate([np.load(p) for p in Path(directory).glob("*.npy")])
    for run in result["runs"]:
        measured = [run[k] for k in ("simulator_bound", "policy", "simulator_bound_after", "latency_model", "lockstep")
                    if k in run]
        measured += [run["simulator_bound_replay"]] if "simulator_bound_replay" in run else []
        measured += [repeat[k] for repeat in run.get("repeats", []) for k in ("policy", "simulator_bound_replay", "simulator_bound")
                     if k in repeat]
        for r in measured:
            r["worker_time"] = worker_time(records, r["span"], run["num_envs"])
            print(f"N={run['num_envs']} {r['episodes_per_hour']} episodes/h: " + ", ".join(
                f"{k} {v['cpu_ms']} CPU ms/call ({v['cpu_s_per_worker']} s/worker)" for k, v in r["worker_time"].items()))
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
