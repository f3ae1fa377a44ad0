#!/usr/bin/env bash
# The closed-loop cells of tab:efficiency_pi05 (issue 33) on one CUDA GPU: each cell of
# config/efficiency_pi05.yaml through `vqb rollout` (the real runner, one LIBERO slot), into
# PROJECT/results/cells/<hash>/, then copied under PROJECT/efficiency_pi05/<ref>/ (the layout of the
# committed results/efficiency_pi05, which `records_dir` reads; `vqb manifest results/efficiency_pi05
# -o manifests/efficiency_pi05.tsv` writes its manifest). Cells in order of need: a cell cut short by
# a time limit resumes from its journal on the next run. The records, packed after every cell into one tar
# (a device call returns no folder nested this deep): TAR, by default PROJECT/efficiency_pi05.tar; on a device call
# put it under $OUT, and here `tar -xf` it into results/ (its members are efficiency_pi05/<ref>/...).
#   MUJOCO_GL=egl TAR=$OUT/efficiency_pi05.tar bash benchmarks/gpu_efficiency_cells.sh /tmp/project  # ~50 s a cell
set -u
project=${1:?usage: gpu_efficiency_cells.sh PROJECT_FOLDER}
tar_file=${TAR:-$project/efficiency_pi05.tar}
cells=(rtn-BASELINE-e2e fp8-W8A8-e2e int8_dynamic-W8A8-e2e int4wo-W4-e2e rtn-FP8E4M3-e2e rtn-W8A8-e2e)  # real kernels first
for cell in "${cells[@]}"; do
  ref=libero/libero_spatial/pi05/$cell
  start=$(date +%s)
  python3 -m vlaquantbench.cli rollout "$ref" --config config/efficiency_pi05.yaml --results "$project" --num-envs 1 \
    || echo "FAILED $ref"
  hash=$(python3 -m vlaquantbench.cli rollout "$ref" --config config/efficiency_pi05.yaml --results "$project" --show \
         | python3 -c 'import json, sys; print(json.load(sys.stdin)["config_hash"])')
  if [ -f "$project/results/cells/$hash/episodes.parquet" ]; then
    mkdir -p "$project/efficiency_pi05/$ref"
    cp "$project/results/cells/$hash/header.json" "$project/results/cells/$hash/episodes.parquet" "$project/efficiency_pi05/$ref/"
    # After every cell (a time limit may stop the next one), whole or not at all (the limit may fall mid-write).
    tar -cf "$tar_file.part" -C "$project" efficiency_pi05 && mv "$tar_file.part" "$tar_file"
  fi
  echo "$ref: $(( $(date +%s) - start )) s"
done
