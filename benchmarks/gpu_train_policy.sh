#!/bin/bash
# Run on the GPU machine from the repository root with the worktree copied to .gpuwork/train and the
# Meta-World stack (benchmarks/simstack.py, issue 30) in .gpuwork/demos-stack, both carried:
#   run(command="bash .gpuwork/train/benchmarks/gpu_train_policy.sh", carry=[".gpuwork/train", ".gpuwork/demos-stack"])
# One device call: demonstrations + training through Snakemake, then the closed-loop check; outputs under $OUT.
set -o pipefail
S=$PWD/.gpuwork/demos-stack
cd .gpuwork/train || exit 1
T0=$(date +%s)
python3 benchmarks/simstack.py unpack --from $S --target /tmp/sim > $OUT/unpack.log 2>&1 || { tail -20 $OUT/unpack.log; exit 1; }
. /tmp/sim/env.sh
export PYTHONPATH=$PWD/src:$PYTHONPATH PYTHONUNBUFFERED=1 MUJOCO_GL=egl
nvidia-smi -L; echo "unpacked $(( $(date +%s)-T0 ))s"
timeout $(( 505-($(date +%s)-T0) )) python3 -m snakemake --cores 16 --scheduler greedy checkpoints/pi05_metaworld/training.json \
  --configfile config/trained_study.yaml > $OUT/snakemake.log 2>&1
echo "snakemake rc=$? at $(( $(date +%s)-T0 ))s"; tail -4 $OUT/snakemake.log; grep -h "step \|time limit\|policy:" logs/train_policy.log | tail -30
if [ -f checkpoints/pi05_metaworld/training.json ]; then
  timeout $(( 575-($(date +%s)-T0) )) python3 benchmarks/trained_policy_closed_loop.py --device cuda --workers 16 --episodes 3 \
    --tasks button-press-topdown-v3 button-press-v3 coffee-button-v3 door-open-v3 door-close-v3 drawer-open-v3 \
    drawer-close-v3 handle-press-v3 window-open-v3 window-close-v3 --out $OUT/closed_loop.json > $OUT/eval.log 2>&1
  echo "eval rc=$? at $(( $(date +%s)-T0 ))s"; grep -v "WARNING\|torchcodec" $OUT/eval.log | tail -30
  tar -cf - checkpoints/pi05_metaworld | split -b 15M - $OUT/ckpt.tar.part
fi
tar -czf $OUT/logs.tar.gz logs results/demonstrations/metaworld/demonstrations.json results/demonstrations/metaworld/manifest.tsv 2>/dev/null
ls -la $OUT; echo "done $(( $(date +%s)-T0 ))s"
