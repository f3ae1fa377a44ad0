#!/bin/bash
# One device call: the trained policy from nothing, within the command limit (600 s). Run on the GPU machine
# from the repository root, with the Meta-World stack (benchmarks/simstack.py pack --benchmark metaworld) in
# .gpuwork/demos-stack, carried:
#   run(command="bash benchmarks/gpu_train_policy.sh", carry=[".gpuwork/demos-stack"])
# (tree and stack within the 64 MiB a call carries: leave the committed records and checkpoints out of the
# index for the call, `git rm -r --cached` and .git/info/exclude, and `git reset` after.)
# 1. the training step's rate by precision and batch (benchmarks/gpu_train_step.py);
# 2. rule demonstrations through Snakemake (config/trained_study.yaml: 10 tasks x 50 episodes, 16 workers);
# 3. rule train_policy through Snakemake, its steps sized from step 1's rate to end by TRAIN_END_S;
# 4. the closed-loop check: 10 tasks x 20 held-out variations (0..19) at full precision
#    (benchmarks/trained_policy_closed_loop.py), episodes recorded as they finish.
# Each phase runs in its own process group, killed whole at its limit (a timed-out Snakemake waits for its
# jobs). Under $OUT: the checkpoint (tar split in 15 MiB parts), closed_loop.json and .jsonl (each episode as
# it ends), logs.tar.gz (refreshed every 20 s and after every phase), timings.txt. TRAIN_END_S=... for a
# shorter call.
set -o pipefail
TRAIN_END_S=${TRAIN_END_S:-440}  # seconds after the start by which training must be done
# torch.compile modes step 1 measures beside eager ("none"): compiling takes minutes (benchmarks/results/gpu_train_policy/).
COMPILE_MODES=${COMPILE_MODES:-none}
S=$PWD/.gpuwork/demos-stack
T0=$(date +%s)
at() { echo "$1 at $(( $(date +%s) - T0 )) s" | tee -a $OUT/timings.txt; }
left() { echo $(( $1 - ($(date +%s) - T0) )); }
save_logs() {
  tar -czf $OUT/.logs.tmp logs results/demonstrations/metaworld/demonstrations.json \
    results/demonstrations/metaworld/manifest.tsv 2>/dev/null; mv -f $OUT/.logs.tmp $OUT/logs.tar.gz
}
# phase LIMIT_S LOG COMMAND...: the command in a process group of its own, killed whole after LIMIT_S.
phase() {
  local limit=$1 log=$2; shift 2
  setsid "$@" > "$log" 2>&1 &
  local pid=$!
  ( sleep "$limit"; kill -TERM -- -$pid 2>/dev/null; sleep 5; kill -KILL -- -$pid 2>/dev/null ) &
  local dog=$!
  wait $pid; local rc=$?
  kill $dog 2>/dev/null; save_logs
  return $rc
}
mkdir -p logs
python3 benchmarks/simstack.py unpack --from $S --target /tmp/sim > logs/unpack.log 2>&1 || { tail -20 logs/unpack.log; exit 1; }
. /tmp/sim/env.sh
export PYTHONPATH=$PWD/src:$PYTHONPATH PYTHONUNBUFFERED=1 MUJOCO_GL=egl
( while sleep 20; do save_logs; done ) &
nvidia-smi -L | tee -a $OUT/timings.txt; at unpacked
phase 240 logs/step_rate.log python3 benchmarks/gpu_train_step.py --out logs/step_rate.json --steps 30 --compile-modes $COMPILE_MODES
at "step rate (rc $?)"; grep '^{' logs/step_rate.log
phase 200 logs/snakemake_demonstrations.log python3 -m snakemake --cores 16 --scheduler greedy \
  results/demonstrations/metaworld/manifest.tsv --configfile config/trained_study.yaml
at "demonstrations (rc $?)"; grep "episodes kept\|episodes tried" logs/demonstrations/metaworld.log | tail -2
[ -f results/demonstrations/metaworld/manifest.tsv ] || { tail -30 logs/demonstrations/metaworld.log; exit 1; }
# The variant with the most samples a second at batch 128, or at 256 when that gives 1.4x the samples;
# its steps fill the time left, less what loading the dataset (~30 s) and compiling (the variant's first steps) take.
python3 - "$(left $(( TRAIN_END_S - 30 )))" > logs/sized.yaml <<'PY'
import json, sys, yaml
budget = float(sys.argv[1])
rows = json.load(open("logs/step_rate.json"))["variants"]
best = {b: max((r for r in rows if r["batch_size"] == b), key=lambda r: r["samples_per_s"])
        for b in {r["batch_size"] for r in rows}}
pick = best[256] if 256 in best and (128 not in best or best[256]["samples_per_s"] >= 1.4 * best[128]["samples_per_s"]) else best[128]
compiling = pick["first_5_steps_s"] if pick["compile_mode"] else 0  # a warm cache makes it less
steps = int(0.92 * pick["steps_per_s"] * (budget - compiling))
config = yaml.safe_load(open("config/trained_study.yaml"))["training"]
print(yaml.safe_dump({"training": {"steps": steps, "batch_size": pick["batch_size"], "precision": pick["precision"],
                                   "compile_mode": pick["compile_mode"], "time_limit_s": budget + 15,
                                   "policy": {**config["policy"], "decay_steps": steps}}}))
PY
grep -v "^    \|^  policy" logs/sized.yaml
phase "$(left $(( TRAIN_END_S + 40 )))" logs/snakemake_training.log python3 -m snakemake --cores 16 --scheduler greedy \
  checkpoints/pi05_metaworld/training.json --configfile config/trained_study.yaml logs/sized.yaml
at "training (rc $?)"; grep "dataset on\|policy:\|step \|time limit\|stopped" logs/train_policy.log | tail -8
if [ -f checkpoints/pi05_metaworld/training.json ]; then
  tar --exclude resume -cf - checkpoints/pi05_metaworld | split -b 15M - $OUT/ckpt.tar.part
  phase "$(left 585)" logs/closed_loop.log python3 benchmarks/trained_policy_closed_loop.py --home checkpoints/pi05_metaworld \
    --device cuda --workers 16 --episodes 20 --first-variation 0 --max-steps 150 \
    --tasks button-press-topdown-v3 button-press-v3 coffee-button-v3 door-open-v3 door-close-v3 drawer-open-v3 \
    drawer-close-v3 handle-press-v3 window-open-v3 window-close-v3 --out $OUT/closed_loop.json --records $OUT/closed_loop.jsonl
  at "closed loop (rc $?)"; python3 -c "
import json, collections; rows = [json.loads(l) for l in open('$OUT/closed_loop.jsonl')]; c = collections.Counter()
for r in rows: c[r['task_name']] += r['success']
print(len(rows), 'episodes,', sum(c.values()), 'successes:', dict(c))"
fi
save_logs; ls -la $OUT; at done
