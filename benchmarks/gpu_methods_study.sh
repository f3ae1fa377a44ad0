#!/usr/bin/env bash
# The methods study of issue 31 item 7 (tables/methods_2026.tex) on the GPU machine: the whole study DAG of
# config/trained_cpu.yaml (the CPU-trained pi0.5, 21 cells and their calibrations) through Snakemake, then
# every finished cell copied under methods_2026/<ref>/ (the layout of the committed results/methods_2026
# that the config's `records_dir` reads) into OUT_DIR/methods_2026.tar, the logs into OUT_DIR/logs.tar:
#   MUJOCO_GL=egl bash benchmarks/gpu_methods_study.sh OUT_DIR [CORES]
# Then, on the project machine: tar -xf methods_2026.tar -C results/ &&
#   vqb manifest results/methods_2026 -o manifests/methods_2026.tsv &&
#   snakemake --cores 2 tables/methods_2026.tex --configfile config/trained_cpu.yaml
# The 2.7 M-parameter policy runs on one CPU thread per cell (study.runner.device cpu, as it was trained and
# evaluated in issue 30); Meta-World renders through EGL on the GPU. A cell is a CPU job of 2 threads, so
# CORES/2 cells run at once (on the one GPU, cuda cells would run one at a time). PuLP is not carried:
# Snakemake's greedy scheduler.
set -u -o pipefail
out=${1:?usage: gpu_methods_study.sh OUT_DIR [CORES]}
cores=${2:-16}
export MUJOCO_GL=${MUJOCO_GL:-egl}
mkdir -p "$out"
# Run the cells instead of reading the committed records; execution settings are not hashed (same cells).
cat > "$out/run_cells.yaml" <<'EOF'
records_dir: null
manifest: null
study:
  execution: {num_envs: 3, torch_threads: 1, progress: false}
EOF
start=$(date +%s)
# Snakemake stops (SIGTERM: running cells keep their journals) before the device call's limit, so the
# finished cells are always tarred; mem_mb unbounded: the memory model's LIBERO worker footprint is not
# Meta-World's, and the machine holds 8 cells easily.
timeout --signal=TERM "${SNAKEMAKE_LIMIT_S:-470}" python3 -m snakemake tables/methods_2026.tex --cores "$cores" \
  --scheduler greedy --keep-going --resources mem_mb=100000000 --configfile config/trained_cpu.yaml "$out/run_cells.yaml"
status=$?
echo "snakemake exit $status after $(( $(date +%s) - start )) s"
stage=$(mktemp -d)  # outside OUT_DIR: only its tar files are meant to come back
python3 - "$stage" <<'EOF'
import json, shutil, sys
from pathlib import Path

stage = Path(sys.argv[1])
for header in sorted(Path("results/cells").glob("*/header.json")):
    episodes = header.with_name("episodes.parquet")
    if episodes.is_file():
        ref = json.loads(header.read_text())["ref"]
        folder = stage / "methods_2026" / ref
        folder.mkdir(parents=True, exist_ok=True)
        for file in (header, episodes):
            shutil.copy2(file, folder / file.name)
        print("recorded", ref, header.parent.name)
EOF
# One tar file each: the machine's output folder returns nothing nested deeper than two folders.
tar -cf "$out/methods_2026.tar" -C "$stage" methods_2026
tar -cf "$out/logs.tar" logs .snakemake/log tables 2>/dev/null
ls -la "$out"
exit $status
