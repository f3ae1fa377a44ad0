"""Collect the headline numbers of the GPU benchmarks into `benchmarks/results/summary.json`.

Reads (each written on the GPU machine by its script) `gpu_preset_ab_cameras{2,3}.json` and
`gpu_policy_inference_cameras2.json` (`gpu_policy_inference.py`), `gpu_real_kernels.json` and
`closed_loop_gpu*.json`, `gpu_fp8_real*.json` (FP8, INT8 and INT4) and `gpu_hadamard_captured*.json`
(W4A4 + Hadamard), and copies out the keys issues 6, 15, 31 and 33 ask for, each with the machine it
was measured on. The policy's headline numbers are at LIBERO's two cameras, the input of every
closed-loop run; the three-camera input of pi0.5's base configuration stands beside them.

    python benchmarks/gpu_summary.py
"""

from __future__ import annotations

import json
import statistics
from collections import defaultdict
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
# The latency and overhead values: BASELINE and W4A4 models taking turns in one process
# (`--preset-ab`), so that the machine's drift does not fall on one preset; per camera count.
PRESET_AB = {2: "gpu_preset_ab_cameras2.json", 3: "gpu_preset_ab_cameras3.json"}
# Eager times, capture (warm-up) times and throughput: the presets one after the other.
POLICY = "gpu_policy_inference_cameras2.json"
GRID_EPISODES = 94_574  # the paper's 409 runs


def _envs(item: tuple[str, list]) -> int:
    return int(item[0].rsplit("_", 1)[1])


def _closed_loop() -> dict:
    """Closed-loop keys from every `closed_loop_gpu*.json` of `gpu_closed_loop.py` (GPU machine; one
    file per device call): the best episodes per hour and the grid estimate; the ratio to the
    simulator alone on the same episodes (`_vs_replay_bound`) with, beside it, the best run's ratio to
    the random-action bound; every run's episodes per hour and ratios by number of environments."""
    files = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("closed_loop_gpu*.json"))]
    runs = [(run, f) for f in files for run in f.get("runs", [])]
    if not runs:
        return {}
    best, source = max(runs, key=lambda r: r[0]["policy"]["episodes_per_hour"])
    where = _closed_loop_machine(source["machine"])
    setup = (f"{source['suite']}, pi0.5 {source['variant']} weights {source['dtype']}, {source['inference']['sampler']} "
             f"sampler, {source['max_steps']} steps per episode, camera {source['camera_size']} px, chunk-at-a-time "
             "workers, policy overlapped with stepping")
    # Every run per N, oldest first: single runs on one machine spread by up to 0.15 in their ratio.
    by_n, bound_by_n = defaultdict(list), defaultdict(list)
    for run, f in sorted(runs, key=lambda r: r[1]["machine"]["date_utc"]):
        by_n[f"num_envs_{run['num_envs']}"].append(run["policy"]["episodes_per_hour"])
        bound_by_n[f"num_envs_{run['num_envs']}"].append(run["vs_simulator_bound"])
    by_n, bound_by_n = dict(sorted(by_n.items(), key=_envs)), dict(sorted(bound_by_n.items(), key=_envs))
    hours = GRID_EPISODES / best["policy"]["episodes_per_hour"]
    random_actions = {"value": best["vs_simulator_bound"], "num_envs": best["num_envs"],
                      # The mean of the bounds measured before and after the policy, where both were.
                      "simulator_bound_episodes_per_hour": best.get("simulator_bound_episodes_per_hour",
                                                                    best["simulator_bound"]["episodes_per_hour"]),
                      "by_num_envs": bound_by_n, "machine": where}
    return {
        "closed_loop_episodes_per_hour": {"value": best["policy"]["episodes_per_hour"], "num_envs": best["num_envs"],
                                          "by_num_envs": by_n, "goal": ">= 3000", "machine": where, "setup": setup},
        "closed_loop_vs_sim_bound": _vs_replay_bound(runs) | {"goal": ">= 0.9", "random_action_bound": random_actions},
        "closed_loop_grid_gpu_hours": {"value": round(hours, 1), "note": f"{GRID_EPISODES} episodes (409 runs) at "
                                       f"{best['policy']['episodes_per_hour']} episodes/h, every episode to its step "
                                       "limit (an upper bound: successful episodes end early)", "machine": where},
    }


def _vs_replay_bound(runs: list[tuple[dict, dict]]) -> dict:
    """The policy against the simulator alone on the same episodes: each policy run's episodes/h over
    that of the zero-cost run replaying its actions (`--replay-bound`). The value is the lowest
    run's median, over every run that measured it; the random-action bound stands beside it."""
    replayed = [(run, f) for run, f in runs if "vs_replay_bound" in run]
    if not replayed:
        return {}
    by_n = defaultdict(list)
    for run, f in sorted(replayed, key=lambda r: r[1]["machine"]["date_utc"]):
        by_n[f"num_envs_{run['num_envs']}"].append([pair["ratio"] for pair in run["replay_pairs"]])
    worst, source = min(replayed, key=lambda r: r[0]["vs_replay_bound"])
    return {"value": worst["vs_replay_bound"], "num_envs": worst["num_envs"],
            "bound": "a zero-cost policy replaying each policy run's own actions, episode by episode (same tasks, "
                     "init states and executed actions, checked by digest), measured right after that run",
            "replay_pairs": worst["replay_pairs"], "by_num_envs": dict(sorted(by_n.items(), key=_envs)),
            "machine": _closed_loop_machine(source["machine"])}


def _closed_loop_machine(machine: dict) -> str:
    return (f"{machine['gpu']}, {machine['cpus']} cores, EGL rendering on the GPU, torch {machine['versions']['torch']}, "
            f"MuJoCo {machine['versions']['mujoco']}, {machine['date_utc']}")


def _fp8_real() -> dict:
    """Issue 33's keys from `gpu_fp8_real*.json` (`gpu_fp8_real.py`, one file per device call): real
    FP8 kernels against the BF16 captured baseline and FP8 fake quantization, the three cells taking
    turns in one process. Each value is the median over the runs (the typical run), every run beside it."""
    every = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("gpu_fp8_real*.json"))]
    # A run cut by its time limit before the timed turns (it writes after every stage) gives its
    # memory and actions, not chunk times.
    runs = [run for run in every if "chunk_ms" in run]
    if not runs:
        return {}
    where = "; ".join(_machine(run) for run in runs)
    form = (f"captured, {runs[0]['cameras']} cameras, bf16 / fp8-W8A8-e2e / rtn-FP8E4M3-e2e taking turns "
            f"({runs[0]['rounds']} rounds x {runs[0]['repeats_per_round']} chunks each, median), {len(runs)} runs")

    def typical(values: list[float]) -> dict:
        return {"value": statistics.median(values), "by_run": values}

    goals = {1: "<= 1.0", 8: "<= 0.85", 32: "<= 0.75"}
    ms = [run["chunk_ms"] for run in runs]
    memory = runs[-1]["weight_memory"]
    rel_l2 = runs[-1]["actions_rel_l2"]
    return {
        **{f"fp8real_vs_bf16_b{b}": {**typical([m["fp8real"][str(b)] / m["bf16"][str(b)] for m in ms]),
                                     "fp8real_ms": [m["fp8real"][str(b)] for m in ms], "bf16_ms": [m["bf16"][str(b)] for m in ms],
                                     "fakequant_ms": [m["fakequant"][str(b)] for m in ms],
                                     "form": form, "goal": goals[b], "machine": where} for b in (1, 8, 32)},
        "fp8real_chunk_ms_b1": {**typical([m["fp8real"]["1"] for m in ms]), "cameras": runs[0]["cameras"], "goal": "<= 16",
                                "machine": where},
        "fp8real_weight_memory_ratio": {
            "value": memory["fp8real_vs_bf16_released"], "vs_all_bf16": memory["fp8real_vs_all_bf16"],
            "note": f"the {memory['layers']} quantized linears' storages (FP8 weights, float32 scales, biases as "
                    "released) over the same layers as released (bf16; SigLIP tower and projector float32); "
                    "vs_all_bf16: over their bf16 size", "goal": "<= 0.55", "machine": where},
        "fp8real_vs_fakequant_rel_l2": {
            "value": max(rel_l2["fp8real_vs_fakequant"].values()), "by_batch": rel_l2["fp8real_vs_fakequant"],
            "fp8real_vs_bf16": rel_l2["fp8real_vs_bf16"], "fakequant_vs_bf16": rel_l2["fakequant_vs_bf16"],
            "note": "actions of one chunk on the same random inputs and weights (largest over batches 1, 8, 32)",
            "goal": "<= 2e-2", "machine": where},
    }


def _int_real() -> dict:
    """Issue 33's INT8 (W8A8, `int8real`) and INT4 (W4A16, `int4`) keys from the `gpu_fp8_real*.json`
    runs that measured them, beside BF16 in the same process, as `_fp8_real`'s: weight memory and
    actions from the latest such run, chunk-time ratios from the runs that reached the timed turns
    (None, saying so, where none did)."""
    runs = [run for run in (json.loads(p.read_text()) for p in sorted(RESULTS.glob("gpu_fp8_real*.json")))
            if "int8real_gib" in run.get("weight_memory", {})]
    if not runs:
        return {}
    timed = [run for run in runs if "chunk_ms" in run]
    memory, rel_l2, where = runs[-1]["weight_memory"], runs[-1]["actions_rel_l2"], _machine(runs[-1])
    not_timed = {"value": None, "note": "not measured: the only run with these cells reached its time limit before "
                                        "the timed turns (gpu_fp8_real_run3.log)", "machine": where}
    out = {}
    for name, goal in (("int8real", "<= 0.55"), ("int4", "<= 0.3")):
        for b in (1, 8, 32):
            ratios = [run["chunk_ms"][name][str(b)] / run["chunk_ms"]["bf16"][str(b)] for run in timed]
            out[f"{name}_vs_bf16_b{b}"] = not_timed if not timed else {
                "value": statistics.median(ratios), "by_run": ratios, "machine": "; ".join(map(_machine, timed))}
        out[f"{name}_chunk_ms_b1"] = not_timed if not timed else {
            "value": statistics.median(run["chunk_ms"][name]["1"] for run in timed), "machine": "; ".join(map(_machine, timed))}
        out[f"{name}_weight_memory_ratio"] = {
            "value": memory[f"{name}_vs_bf16_released"], "vs_all_bf16": memory[f"{name}_vs_all_bf16"],
            "note": f"the {memory['layers']} quantized linears' storages over the same layers as released "
                    "(bf16; SigLIP tower and projector float32); vs_all_bf16: over their bf16 size",
            "goal": goal, "machine": where}
    out["int8real_vs_fakequant_rel_l2"] = {
        "value": max(rel_l2["int8real_vs_fakequant_int8"].values()), "by_batch": rel_l2["int8real_vs_fakequant_int8"],
        "int8real_vs_bf16": rel_l2["int8real_vs_bf16"], "fakequant_int8_vs_bf16": rel_l2["fakequant_int8_vs_bf16"],
        "note": "int8_dynamic-W8A8-e2e against rtn-W8A8-e2e (same grid, fake-quantized), one chunk on the same "
                "random inputs and weights (batch 1)", "goal": "<= 2e-2", "machine": where}
    out["int4_vs_bf16_rel_l2"] = {"value": max(rel_l2["int4_vs_bf16"].values()), "by_batch": rel_l2["int4_vs_bf16"],
                                  "note": "int4wo-W4-e2e (asymmetric groups of 128) against BF16", "machine": where}
    return out


# Runs of `gpu_hadamard_captured.py` whose BASELINE cell is no reference, and why: their W4A4 and
# Hadamard cells still compare side by side (`hadamard_vs_w4a4`).
BASELINE_NOT_A_REFERENCE = {
    "gpu_hadamard_captured_run3.json": "its kernel microbenchmark compiled the sampler's gated_add_ada_rms_norm "
    "and merge_heads again in every call, past dynamo's recompile limit, so the chunks ran those functions "
    "uncompiled where they compile them unquantized: BASELINE at every layer (21.6 ms at batch 1 against 19.2-19.9 "
    "in the other runs), the quantized cells only at the expert's final norm (10 calls a chunk, both cells alike); "
    "fixed in the script since",
}
# The rotation kernels each run measured (`gpu_hadamard_captured*.json`, by file).
HADAMARD_KERNELS = {
    "gpu_hadamard_captured.json": "norm / head merge compiled by inductor, then the rotation kernel",
    "gpu_hadamard_captured_run2.json": "norm / head merge compiled by inductor, then the rotation kernel",
    "gpu_hadamard_captured_run3.json": "norm / head merge, rotation and quantization in one kernel (rotated_norms), "
                                       "the Hadamard signs read, not derived; the expert's GELU with 4 warps (now 8)",
    "gpu_hadamard_captured_run4.json": "as run3, the expert's GELU with 8 warps (main's kernels, 2026-12-05)",
    "gpu_hadamard_captured_run5.json": "as run3, the expert's GELU with 8 warps (main's kernels, 2026-12-05)",
}
# The runs of main's kernels: the value is their median (earlier runs measured earlier kernels).
CURRENT_KERNELS = ("gpu_hadamard_captured_run4.json", "gpu_hadamard_captured_run5.json")


def _hadamard_captured() -> dict:
    """Issue 31's keys from `gpu_hadamard_captured*.json` (`gpu_hadamard_captured.py`, one file per
    device call): W4A4 + Hadamard (rotations inside the captured chunk) over BASELINE, the cells
    taking turns in one process, with plain W4A4 of the same run beside it. The value is the median
    over the runs of main's kernels (`CURRENT_KERNELS`) whose BASELINE is a reference
    (`BASELINE_NOT_A_REFERENCE`), those runs beside it;
    `hadamard_vs_w4a4` is the Hadamard cell over plain W4A4 in every run, with the kernels it ran
    (`HADAMARD_KERNELS`)."""
    runs = {path.name: run for path, run in ((p, json.loads(p.read_text()))
                                             for p in sorted(RESULTS.glob("gpu_hadamard_captured*.json")))
            if "chunk_ms" in run}
    if not runs:
        return {}
    referenced = {name: run for name, run in runs.items()
                  if name not in BASELINE_NOT_A_REFERENCE and name in CURRENT_KERNELS}
    first = next(iter(runs.values()))
    where = "; ".join(_machine(run) for run in runs.values())
    form = (f"captured, {first['cameras']} cameras, BASELINE / rtn-W4A4-e2e / hadamard-W4A4-e2e taking turns "
            f"({first['rounds']} rounds x {first['repeats_per_round']} chunks each, median); value: median of "
            f"{', '.join(referenced)}; the VLM residual stream rotated offline (quant.rotation), every other "
            "selected input rotated online inside the captured chunk, fused with the op producing it")
    out = {}
    for b in (1, 8, 32):
        ratios = [run["vs_baseline"]["w4a4_hadamard"][str(b)] for run in referenced.values()]
        out[f"fakequant_w4a4_hadamard_e2e_overhead_b{b}"] = {
            "value": statistics.median(ratios), "by_run": ratios,
            "plain_w4a4_value": statistics.median(run["vs_baseline"]["w4a4"][str(b)] for run in referenced.values()),
            "hadamard_ms": [run["chunk_ms"]["w4a4_hadamard"][str(b)] for run in referenced.values()],
            "baseline_ms": [run["chunk_ms"]["baseline"][str(b)] for run in referenced.values()],
            "hadamard_vs_w4a4": {name: {"value": run["chunk_ms"]["w4a4_hadamard"][str(b)] / run["chunk_ms"]["w4a4"][str(b)],
                                        "kernels": HADAMARD_KERNELS.get(name, "")} for name, run in runs.items()},
            "not_a_reference": {name: why for name, why in BASELINE_NOT_A_REFERENCE.items() if name in runs},
            "form": form, "goal": "<= 1.10", "machine": where}
    return out


def _machine(result: dict) -> str:
    return f"{result['machine']['gpu']}, torch {result['machine']['torch']}, {result['machine']['date_utc']}"


def main() -> None:
    ab = {cameras: json.loads((RESULTS / name).read_text()) for cameras, name in PRESET_AB.items()}
    ab_ms = {cameras: result["preset_ab"]["median_ms"] for cameras, result in ab.items()}
    policy = json.loads((RESULTS / POLICY).read_text())
    kernels = json.loads((RESULTS / "gpu_real_kernels.json").read_text())
    policy_machine, ab_machine, kernel_machine = _machine(policy), _machine(ab[2]), _machine(kernels)
    cells = {c["preset"]: c for c in policy["cells"]}
    # Warm-up per cell after the first: capturing every batch size again (the compiled kernels are reused).
    later_cells = [c for c in policy["cells"] if c["preset"] != policy["cells"][0]["preset"]]
    warmup_later = max(sum(b["capture_s"] for b in c["captured"].values()) for c in later_cells)
    warmup_first = sum(b["capture_s"] for b in policy["cells"][0]["captured"].values())
    best = None
    for backbone, rows in kernels["backbones"].items():
        for row in rows:
            if row["method"] != "bf16" and "speedup_vs_bf16" in row:
                if best is None or row["speedup_vs_bf16"] > best[2]["speedup_vs_bf16"]:
                    best = (backbone, row["method"], row)
    summary = {
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
                              # None: a run from before the script recorded it
                              "inductor_cache_files_at_start": policy.get("inductor_cache_files_at_start"),
                              "goal": "<= 60", "machine": policy_machine},
        **{f"fakequant_w4a4_e2e_overhead_b{b}": {
            "value": ab[2]["preset_ab"]["vs_BASELINE"]["W4A4"][str(b)], "cameras": 2,
            "three_cameras_value": ab[3]["preset_ab"]["vs_BASELINE"]["W4A4"][str(b)],
            "presets_one_after_the_other_value": cells["W4A4"]["captured"][str(b)]["median_ms"]
            / cells["BASELINE"]["captured"][str(b)]["median_ms"],
            "eager_value": cells["W4A4"]["eager"][str(b)]["median_ms"] / cells["BASELINE"]["eager"][str(b)]["median_ms"],
            "form": "captured, BASELINE and W4A4 taking turns", "goal": "<= 1.05", "machine": ab_machine}
           for b in (1, 8, 32)},
        "best_real_kernel": {"value": f"{best[1]} on {best[0]}", "format": best[2]["format"],
                             "form": best[2].get("full_inference_form"), "machine": kernel_machine},
        "best_real_kernel_speedup_vs_bf16": {"value": best[2]["speedup_vs_bf16"], "goal": ">= 1.3",
                                             "machine": kernel_machine},
        **_closed_loop(),
        **_fp8_real(),
        **_int_real(),
        **_hadamard_captured(),
    }
    (RESULTS / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
