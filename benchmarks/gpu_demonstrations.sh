#!/usr/bin/env bash
# Rule demonstrations on the GPU machine, through Snakemake, on the carried Meta-World stack
# (benchmarks/simstack.py pack --benchmark metaworld). Run from the project copy's root:
#   bash benchmarks/gpu_demonstrations.sh STACK EPISODES_PER_TASK OUT [LIMIT_S]
# (LIMIT_S, default 540: Snakemake's time limit, within a device call's 600 s. The run of 2026-12-04 used
# 150 s and was stopped one second after its 100th episode: benchmarks/results/gpu_demonstrations_h200/.)
# Writes to OUT: the Snakemake log, the rule's log and benchmark, demonstrations.json, manifest.tsv,
# what renders EGL (GL_RENDERER), the GPU's load sampled every 2 s, and the timings.
set -uo pipefail
stack=$1 episodes=$2 out=$3 limit=${4:-540}
now() { python3 -c "import time; print(time.time())"; }
started=$(now)
target=${SIM_TARGET:-/tmp/sim}
python3 benchmarks/simstack.py unpack --from "$stack" --target "$target" > "$out/unpack.log" 2>&1 || exit 1
. "$target/env.sh"
export PYTHONPATH=$PWD/src:$PYTHONPATH
unpacked=$(now)
{ nvidia-smi -L; echo "cores: $(nproc)"; python3 -c "import av, lerobot, mujoco, snakemake, metaworld
for m in (av, lerobot, mujoco, snakemake, metaworld): print(m.__name__, m.__file__)"; } > "$out/machine.txt" 2>&1
# Which OpenGL implementation MuJoCo's EGL context gets: NVIDIA's (the GPU) or a software one.
python3 -c "import mujoco; from OpenGL import GL
context = mujoco.GLContext(64, 64); context.make_current()
print('GL_VENDOR', GL.glGetString(GL.GL_VENDOR).decode(), '| GL_RENDERER', GL.glGetString(GL.GL_RENDERER).decode()); context.free()" > "$out/egl.txt" 2>&1
python3 - "$episodes" > /tmp/reduced.yaml <<'PY'
import sys, yaml
config = yaml.safe_load(open("config/trained_study.yaml"))
print(yaml.safe_dump({"demonstrations": {**config["demonstrations"], "episodes_per_task": int(sys.argv[1])}}))
PY
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv -l 2 > "$out/gpu_load.csv" 2>&1 &
sampler=$!
(sleep 30; nvidia-smi > "$out/nvidia-smi-during.txt" 2>&1) &
timeout "$limit" python3 -m snakemake results/demonstrations/metaworld/manifest.tsv --cores "$(nproc)" --scheduler greedy \
  --configfile config/trained_study.yaml /tmp/reduced.yaml > "$out/snakemake.log" 2>&1
status=$?
finished=$(now)
nvidia-smi > "$out/nvidia-smi-after.txt" 2>&1
kill "$sampler"
cp logs/demonstrations/metaworld.log logs/demonstrations/metaworld.benchmark.tsv results/demonstrations/metaworld/demonstrations.json \
  results/demonstrations/metaworld/manifest.tsv "$out/" 2>/dev/null
du -sh results/demonstrations/metaworld/dataset > "$out/dataset_size.txt" 2>&1
python3 -c "import json, sys; t0, t1, t2 = map(float, sys.argv[2:]); print(json.dumps({'snakemake_status': int(sys.argv[1]),
  'unpack_s': round(t1 - t0, 1), 'snakemake_s': round(t2 - t1, 1)}))" "$status" "$started" "$unpacked" "$finished" > "$out/timings.json"
cat "$out/timings.json" "$out/egl.txt" "$out/machine.txt"; tail -5 "$out/metaworld.log" 2>/dev/null; tail -3 "$out/snakemake.log"
