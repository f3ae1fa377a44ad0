"""Collect the headline numbers of the GPU benchmarks into `benchmarks/results/summary.json`.

Reads (each written on the GPU machine by its script) `gpu_preset_ab_cameras{2,3}.json` and
`gpu_policy_inference_cameras2.json` (`gpu_policy_inference.py`), `closed_loop_gpu*.json`
(`gpu_closed_loop.py`), `gpu_fp8_real*.json` (`gpu_fp8_real.py`: FP8, INT8 and INT4) and the
`gpu_hadamard_captured*.json` runs of `HADAMARD_RUNS` (`gpu_hadamard_captured.py`), the `KERNEL_RUNS` of
`gpu_kernel_shapes.py` (the current int8, FP8 and int4 kernels), the closed-loop records of the real kernels (the
GPU-trained policy's `TRAINED_KERNELS` cells, pi0.5's efficiency cells under `EFFICIENCY`), and copies out the
headline keys, each with the machine it was measured on. The policy's headline numbers are at
LIBERO's two cameras, the input of every closed-loop run; the three-camera input of pi0.5's base
configuration stands beside them.

    python benchmarks/gpu_summary.py
"""

from __future__ import annotations

import json
import statistics
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "src"))
from vlaquantbench.records import find_cells, read_cell  # noqa: E402
# The latency and overhead values: BASELINE and W4A4 models taking turns in one process
# (`--preset-ab`), so that the machine's drift does not fall on one preset; per camera count.
PRESET_AB = {2: "gpu_preset_ab_cameras2.json", 3: "gpu_preset_ab_cameras3.json"}
# Eager times, capture (warm-up) times and throughput: the presets one after the other.
POLICY = "gpu_policy_inference_cameras2.json"
# The runs of the current rotation kernels (earlier runs timed earlier kernels; HISTORY.md has them).
HADAMARD_RUNS = ("gpu_hadamard_captured_run4.json", "gpu_hadamard_captured_run5.json")
GRID_EPISODES = 94_574  # the paper's 409 runs
BATCHES = (1, 8, 32)


def _load(pattern: str) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(RESULTS.glob(pattern))]


def _machine(result: dict) -> str:
    return f"{result['machine']['gpu']}, torch {result['machine']['torch']}, {result['machine']['date_utc']}"


def _closed_loop_machine(machine: dict) -> str:
    return (f"{machine['gpu']}, {machine['cpus']} cores, EGL rendering on the GPU, torch {machine['versions']['torch']}, "
            f"MuJoCo {machine['versions']['mujoco']}, {machine['date_utc']}")


def _by_num_envs(runs: list[tuple[dict, dict]], value) -> dict:
    """`value(run)` of every run per number of environments, oldest first (single runs on one machine
    spread by up to 0.15 in their ratio)."""
    by_n = defaultdict(list)
    for run, f in sorted(runs, key=lambda r: r[1]["machine"]["date_utc"]):
        by_n[run["num_envs"]].append(value(run))
    return {f"num_envs_{n}": by_n[n] for n in sorted(by_n)}


def _closed_loop() -> dict:
    """The best episodes per hour over every `closed_loop_gpu*.json` run and the grid estimate; the
    policy over the simulator alone on the same episodes (`vs_replay_bound`: the lowest run's median)
    with the best run's ratio to the random-action bound beside it."""
    runs = [(run, f) for f in _load("closed_loop_gpu*.json") for run in f.get("runs", [])]
    if not runs:
        return {}
    best, source = max(runs, key=lambda r: r[0]["policy"]["episodes_per_hour"])
    where = _closed_loop_machine(source["machine"])
    per_hour = best["policy"]["episodes_per_hour"]
    setup = (f"{source['suite']}, pi0.5 {source['variant']} weights {source['dtype']}, {source['inference']['sampler']} "
             f"sampler, {source['max_steps']} steps per episode, camera {source['camera_size']} px, chunk-at-a-time "
             "workers, policy overlapped with stepping")
    replayed = [(run, f) for run, f in runs if "vs_replay_bound" in run]
    worst, worst_source = min(replayed, key=lambda r: r[0]["vs_replay_bound"])
    random_actions = {"value": best["vs_simulator_bound"], "num_envs": best["num_envs"],
                      "simulator_bound_episodes_per_hour": best["simulator_bound_episodes_per_hour"],
                      "by_num_envs": _by_num_envs(runs, lambda run: run["vs_simulator_bound"]), "machine": where}
    return {
        "closed_loop_episodes_per_hour": {"value": per_hour, "num_envs": best["num_envs"],
                                          "by_num_envs": _by_num_envs(runs, lambda run: run["policy"]["episodes_per_hour"]),
                                          "goal": ">= 3000", "machine": where, "setup": setup},
        "closed_loop_vs_sim_bound": {
            "value": worst["vs_replay_bound"], "num_envs": worst["num_envs"],
            "bound": "a zero-cost policy replaying each policy run's own actions, episode by episode (same tasks, "
                     "init states and executed actions, checked by digest), measured right after that run",
            "replay_pairs": worst["replay_pairs"],
            "by_num_envs": _by_num_envs(replayed, lambda run: [pair["ratio"] for pair in run["replay_pairs"]]),
            "machine": _closed_loop_machine(worst_source["machine"]), "goal": ">= 0.9",
            "random_action_bound": random_actions},
        "closed_loop_grid_gpu_hours": {"value": round(GRID_EPISODES / per_hour, 1),
                                       "note": f"{GRID_EPISODES} episodes (409 runs) at {per_hour} episodes/h, every "
                                       "episode to its step limit (an upper bound: successful episodes end early)",
                                       "machine": where},
    }


def _memory_ratio(memory: dict, name: str, goal: str, where: str) -> dict:
    return {"value": memory[f"{name}_vs_bf16_released"], "vs_all_bf16": memory[f"{name}_vs_all_bf16"],
            "note": f"the {memory['layers']} quantized linears' storages over the same layers as released (bf16; "
                    "SigLIP tower and projector float32); vs_all_bf16: over their bf16 size",
            "goal": goal, "machine": where}


def _real_kernels() -> dict:
    """Real FP8, INT8 and INT4 kernels against the BF16 captured baseline and fake quantization, the
    cells taking turns in one process (`gpu_fp8_real*.json`, one file per device call). Chunk-time
    values are the median over the runs that reached the timed turns, every run beside it (None,
    saying so, where none did); weight memory and actions come from the latest run that has them."""
    every = _load("gpu_fp8_real*.json")
    if not every:
        return {}
    out = {}
    for name, cells, goals, memory_goal in (("fp8real", "bf16 / fp8-W8A8-e2e / rtn-FP8E4M3-e2e",
                                             {1: "<= 1.0", 8: "<= 0.85", 32: "<= 0.75"}, "<= 0.55"),
                                            ("int8real", None, {}, "<= 0.55"), ("int4", None, {}, "<= 0.3")):
        measured = [run for run in every if f"{name}_gib" in run.get("weight_memory", {})]
        timed = [run for run in measured if "chunk_ms" in run]
        latest, where = measured[-1], _machine(measured[-1])
        timed_where = "; ".join(map(_machine, timed))
        not_timed = {"value": None, "note": "not measured: the only run with these cells reached its time limit "
                                            "before the timed turns (gpu_fp8_real_run3.log)", "machine": where}
        for b in BATCHES:
            ratios = [run["chunk_ms"][name][str(b)] / run["chunk_ms"]["bf16"][str(b)] for run in timed]
            out[f"{name}_vs_bf16_b{b}"] = not_timed if not timed else {
                "value": statistics.median(ratios), "by_run": ratios,
                **({f"{name}_ms": [run["chunk_ms"][name][str(b)] for run in timed],
                    "bf16_ms": [run["chunk_ms"]["bf16"][str(b)] for run in timed],
                    "fakequant_ms": [run["chunk_ms"]["fakequant"][str(b)] for run in timed],
                    "form": f"captured, {timed[0]['cameras']} cameras, {cells} taking turns ({timed[0]['rounds']} "
                            f"rounds x {timed[0]['repeats_per_round']} chunks each, median), {len(timed)} runs",
                    "goal": goals[b]} if cells else {}),
                "machine": timed_where}
        chunk_b1 = [run["chunk_ms"][name]["1"] for run in timed]
        out[f"{name}_chunk_ms_b1"] = not_timed if not timed else {
            "value": statistics.median(chunk_b1), "by_run": chunk_b1, "cameras": timed[0]["cameras"],
            **({"goal": "<= 16"} if cells else {}), "machine": timed_where}
        out[f"{name}_weight_memory_ratio"] = _memory_ratio(latest["weight_memory"], name, memory_goal, where)
    fp8_l2 = [run for run in every if "chunk_ms" in run][-1]["actions_rel_l2"]
    out["fp8real_vs_fakequant_rel_l2"] = {
        "value": max(fp8_l2["fp8real_vs_fakequant"].values()), "by_batch": fp8_l2["fp8real_vs_fakequant"],
        "fp8real_vs_bf16": fp8_l2["fp8real_vs_bf16"], "fakequant_vs_bf16": fp8_l2["fakequant_vs_bf16"],
        "note": "actions of one chunk on the same random inputs and weights (largest over batches 1, 8, 32)",
        "goal": "<= 2e-2", "machine": "; ".join(_machine(run) for run in every if "chunk_ms" in run)}
    int_run = [run for run in every if "int8real_gib" in run.get("weight_memory", {})][-1]
    int_l2, where = int_run["actions_rel_l2"], _machine(int_run)
    out["int8real_vs_fakequant_rel_l2"] = {
        "value": max(int_l2["int8real_vs_fakequant_int8"].values()), "by_batch": int_l2["int8real_vs_fakequant_int8"],
        "int8real_vs_bf16": int_l2["int8real_vs_bf16"], "fakequant_int8_vs_bf16": int_l2["fakequant_int8_vs_bf16"],
        "note": "int8_dynamic-W8A8-e2e against rtn-W8A8-e2e (same grid, fake-quantized), one chunk on the same "
                "random inputs and weights (batch 1)", "goal": "<= 2e-2", "machine": where}
    out["int4_vs_bf16_rel_l2"] = {"value": max(int_l2["int4_vs_bf16"].values()), "by_batch": int_l2["int4_vs_bf16"],
                                  "note": "int4wo-W4-e2e (asymmetric groups of 128) against BF16", "machine": where}
    return out


# The current kernels' cells, one model at a time beside BF16 in one process (`gpu_kernel_shapes.py`): batches 1
# and 8 (with the mixed int4 assignments), and batch 32 (an earlier call of the same int8 and FP8 kernels there).
KERNEL_RUNS = ("gpu_kernel_e2e.json", "gpu_kernel_e2e_b32.json")
KERNEL_GOALS = {"fp8real": {1: "<= 0.95", 32: "<= 0.75"}, "int8real": {8: "<= 0.85", 32: "<= 0.85"},
                "int4": {1: "<= 0.9"}, "int4_expert_fp8": {1: "<= 0.9"}, "int4_expert_int8": {1: "<= 0.9"}}


def _kernel_cells() -> dict:
    """Chunk time of each real-kernel cell over BF16 measured in the same process (`KERNEL_RUNS`): these keys
    replace `_real_kernels`' for the same cells, whose runs timed earlier kernels (HISTORY.md)."""
    out = {}
    for name in KERNEL_RUNS:
        run = json.loads((RESULTS / name).read_text())
        profile = run["profile"]
        for cell, timed in profile.items():
            if cell == "bf16":
                continue
            for b, ms in timed["chunk_ms"].items():
                bf16 = profile["bf16"]["chunk_ms"][b]
                out[f"{cell}_vs_bf16_b{b}"] = {
                    "value": ms / bf16, f"{cell}_ms": ms, "bf16_ms": bf16,
                    "form": f"captured, {run['cameras']} cameras, one model at a time after BF16 in one process "
                            f"(median of the chunks after capture), {name}",
                    **({"goal": KERNEL_GOALS[cell][int(b)]} if int(b) in KERNEL_GOALS.get(cell, {}) else {}),
                    "actions_rel_l2_vs_bf16": timed["actions_rel_l2_vs_bf16"], "machine": _machine(run)}
            if "1" in timed["chunk_ms"]:
                out[f"{cell}_chunk_ms_b1"] = {"value": timed["chunk_ms"]["1"], "cameras": run["cameras"],
                                              **({"goal": "<= 16 on an H200"} if cell == "fp8real" else {}),
                                              "machine": _machine(run)}
    return out


# Issue 51 item 6: the GPU-trained policy under each real kernel and under fake quantization of the same format, in
# full (config/gpu_kernels.yaml; 200 episodes a cell, the same episodes in every cell): real cell -> fake cell.
TRAINED_KERNELS = ROOT / "results" / "gpu_study" / "fixed"
KERNEL_PAIRS = {"fp8-W8A8-e2e": "rtn-FP8E4M3-e2e", "int8_dynamic-W8A8-e2e": "rtn-W8A8-e2e", "int4wo-W4-e2e": "rtn-W4-e2e"}
# Issue 51 item 5: pi0.5 at full width with random weights, one LIBERO slot (config/efficiency_pi05.yaml).
EFFICIENCY = ROOT / "results" / "efficiency_pi05"


def _records(folder: Path) -> dict:
    """Cell name -> its record (`vlaquantbench.records`) of every cell under `folder`; {} when there is none."""
    return {ref.rsplit("/", 1)[-1]: read_cell(path) for ref, path in find_cells(folder).items()} if folder.is_dir() else {}


def _device(cell) -> str:
    return (f"{cell.header['device']['name']}, {cell.header['host']['cpu']}, torch {cell.header['versions']['torch']}, "
            f"code {cell.header['code_revision'][:12]}")


def _quartiles_ms(seconds) -> dict:
    """The median of per-episode values in seconds, in ms, with the first and third quartiles (the spread)."""
    q1, median, q3 = (1e3 * float(seconds.quantile(q)) for q in (0.25, 0.5, 0.75))
    return {"median": median, "q1": q1, "q3": q3}


def _trained_policy_kernels() -> dict:
    """Success of each real-kernel cell beside its fake-quantized twin (paired on the same episodes: the episodes
    only one of them succeeds on), and each cell's control-call latency: the median of its episodes' means, with
    their quartiles. The records are committed: a missing cell is an error naming it."""
    cells = _records(TRAINED_KERNELS)
    missing = sorted({*KERNEL_PAIRS, *KERNEL_PAIRS.values()} - set(cells))
    if missing:
        raise SystemExit(f"{TRAINED_KERNELS}: no records of {', '.join(missing)} (config/gpu_kernels.yaml's cells)")
    out = {}
    for real, fake in KERNEL_PAIRS.items():
        r, f = (cells[c].episodes.set_index(["task_id", "seed"]).sort_index() for c in (real, fake))
        gained, lost = int((r.success & ~f.success).sum()), int((~r.success & f.success).sum())
        out[f"trained_policy_{real}_success_vs_fake"] = {
            "value": 100 * (r.success.mean() - f.success.mean()), "unit": "pp", "real_success": float(r.success.mean()),
            "fake_success": float(f.success.mean()), "episodes": len(r), "only_real_succeeds": gained,
            "only_fake_succeeds": lost, "fake_cell": fake,
            "real_control_call_ms": _quartiles_ms(r.policy_latency_mean_s),
            "fake_control_call_ms": _quartiles_ms(f.policy_latency_mean_s),
            "form": "GPU-trained pi0.5, 10 Meta-World tasks x variations 0-19, full precision float32 elsewhere "
                    "(tables/gpu_kernels.tex), results/gpu_study/fixed", "machine": _device(cells[real])}
    return out


def _efficiency_cells() -> dict:
    """tab:efficiency_pi05's numbers from its cells' records: peak memory, control-call and full-inference
    latency of each cell, and each over BF16's."""
    cells = _records(EFFICIENCY)
    if "rtn-BASELINE-e2e" not in cells:
        return {}
    values = {name: {"peak_vram_gb": float(c.episodes.peak_vram_gb.max()),
                     "control_call_ms": _quartiles_ms(c.episodes.policy_latency_mean_s),
                     "inference_ms": _quartiles_ms(c.episodes.inference_latency_mean_s)} for name, c in cells.items()}
    bf16 = values["rtn-BASELINE-e2e"]
    return {f"efficiency_pi05_{name}": {
        **v, "inference_vs_bf16": v["inference_ms"]["median"] / bf16["inference_ms"]["median"], "memory_vs_bf16": v["peak_vram_gb"] / bf16["peak_vram_gb"],
        "episodes": cells[name].n_episodes,
        "form": "pi0.5 at full width with random weights, one LIBERO slot, captured sampler (tables/efficiency_pi05.tex), "
                "results/efficiency_pi05", "machine": _device(cells[name])} for name, v in values.items()}


def _hadamard_captured() -> dict:
    """W4A4 + Hadamard (rotations inside the captured chunk) over BASELINE, the cells taking turns in
    one process, with plain W4A4 of the same runs beside it: the median over `HADAMARD_RUNS`."""
    runs = {name: json.loads((RESULTS / name).read_text()) for name in HADAMARD_RUNS}
    first = next(iter(runs.values()))
    form = (f"captured, {first['cameras']} cameras, BASELINE / rtn-W4A4-e2e / hadamard-W4A4-e2e taking turns "
            f"({first['rounds']} rounds x {first['repeats_per_round']} chunks each, median); value: median of "
            f"{', '.join(runs)}; the VLM residual stream rotated offline (quant.rotation), every other "
            "selected input rotated online inside the captured chunk, fused with the op producing it")
    out = {}
    for b in BATCHES:
        ms = [run["chunk_ms"] for run in runs.values()]
        out[f"fakequant_w4a4_hadamard_e2e_overhead_b{b}"] = {
            "value": statistics.median(run["vs_baseline"]["w4a4_hadamard"][str(b)] for run in runs.values()),
            "by_run": [run["vs_baseline"]["w4a4_hadamard"][str(b)] for run in runs.values()],
            "plain_w4a4_value": statistics.median(run["vs_baseline"]["w4a4"][str(b)] for run in runs.values()),
            "hadamard_ms": [m["w4a4_hadamard"][str(b)] for m in ms], "baseline_ms": [m["baseline"][str(b)] for m in ms],
            "hadamard_vs_w4a4": [m["w4a4_hadamard"][str(b)] / m["w4a4"][str(b)] for m in ms],
            "form": form, "goal": "<= 1.10", "machine": "; ".join(map(_machine, runs.values()))}
    return out


def _policy() -> dict:
    ab = {cameras: json.loads((RESULTS / name).read_text()) for cameras, name in PRESET_AB.items()}
    ab_ms = {cameras: result["preset_ab"]["median_ms"] for cameras, result in ab.items()}
    policy = json.loads((RESULTS / POLICY).read_text())
    policy_machine, ab_machine = _machine(policy), _machine(ab[2])
    cells = {c["preset"]: c for c in policy["cells"]}
    # Warm-up per cell after the first: capturing every batch size again (the compiled kernels are reused).
    warmup_later = max(sum(b["capture_s"] for b in c["captured"].values()) for c in policy["cells"][1:])
    warmup_first = sum(b["capture_s"] for b in policy["cells"][0]["captured"].values())
    return {
        "pi05_chunk_ms_b1": {"value": ab_ms[2]["BASELINE"]["1"], "cameras": 2,
                             "three_cameras_ms": ab_ms[3]["BASELINE"]["1"],
                             "form": "captured (CUDA graph, grouped linears, fused elementwise, TF32)",
                             "eager_lerobot_ms": cells["BASELINE"]["eager"]["1"]["median_ms"],
                             "goal": "<= 20", "machine": ab_machine},
        "pi05_chunks_per_s_b32": {"value": cells["BASELINE"]["captured"]["32"]["chunks_per_s"], "cameras": 2,
                                  "goal": ">= 30", "machine": policy_machine},
        "warmup_s_per_cell": {"value": warmup_later, "first_cell_of_process_s": warmup_first,
                              "note": "captures of batch 1, 8 and 32 in one cell, each compiling the fused "
                                      "elementwise/quantization ops for a bit width or batch size new to the "
                                      "process (0.5 s per batch size once compiled); a runner cell captures one",
                              "inductor_cache_files_at_start": policy["inductor_cache_files_at_start"],
                              "goal": "<= 60", "machine": policy_machine},
        **{f"fakequant_w4a4_e2e_overhead_b{b}": {
            "value": ab[2]["preset_ab"]["vs_BASELINE"]["W4A4"][str(b)], "cameras": 2,
            "three_cameras_value": ab[3]["preset_ab"]["vs_BASELINE"]["W4A4"][str(b)],
            "presets_one_after_the_other_value": cells["W4A4"]["captured"][str(b)]["median_ms"]
            / cells["BASELINE"]["captured"][str(b)]["median_ms"],
            "eager_value": cells["W4A4"]["eager"][str(b)]["median_ms"] / cells["BASELINE"]["eager"][str(b)]["median_ms"],
            "form": "captured, BASELINE and W4A4 taking turns", "goal": "<= 1.05", "machine": ab_machine}
           for b in BATCHES},
    }


def main() -> None:
    summary = {**_policy(), **_closed_loop(), **_real_kernels(), **_kernel_cells(), **_trained_policy_kernels(),
               **_efficiency_cells(), **_hadamard_captured()}
    (RESULTS / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
