#!/bin/bash
# The trained policy from nothing on a GPU machine, over warm calls on the same machine:
#   run(command="STEPS=config TRAIN_END_S=545 bash benchmarks/gpu_train_policy.sh", carry=[".gpuwork/demos-stack"])
# then the same command again while the machine is warm (30 s), until $OUT holds ckpt.tar.part*. STEPS=config
# trains config/trained_study.yaml's steps, STEPS=<n> n steps (the cosine decay over them); without it the steps are
# sized from the measured step rate to fill this call plus SECOND_CALL_TRAIN_S (benchmarks/results/gpu_train_policy/
# has each run's calls). The Meta-World stack travels as .gpuwork/demos-stack/part1 (benchmarks/simstack.py pack
# --benchmark metaworld writes .simstack/part1; then mv .simstack .gpuwork/demos-stack); leave the committed records
# and checkpoints out of the index for the call (64 MiB travel). A phase runs only if its output
# is missing, so a second call on the machine (warm 30 s after a call) resumes where the first stopped: step rate
# and graph check (gpu_train_step.py), rule demonstrations, sizing (logs/sized.yaml: the fastest checked variant's
# steps fill this call's training time plus SECOND_CALL_TRAIN_S), rule train_policy until TRAIN_END_S (then its
# resumable state), and with the checkpoint the closed-loop check (10 tasks x variations 0..19). Each phase runs in a
# process group of its own, killed whole at its limit. The first call drops the committed checkpoint (on the device
# machine's copy), so that rule train_policy runs. $OUT: checkpoint tar parts, closed_loop.json(l), logs.tar.gz
# (refreshed every 20 s), timings.txt; after a call that paused the training, paused.tar.part* (the weights, step
# and losses, 39 MB, and the dataset's metadata): if the machine is lost, untar them into the checkout and
# `training.checkpoint_from_saved_state` writes the checkpoint where the state stands.
set -o pipefail
TRAIN_END_S=${TRAIN_END_S:-440}  # seconds into this call by which training stops
SECOND_CALL_TRAIN_S=${SECOND_CALL_TRAIN_S:-0}  # training seconds a second call will add (0: one call)
STEPS=${STEPS:-rate}  # config: the config's steps; a number: that many (and the decay over them); rate: sized from the step rate
S=$PWD/.gpuwork/demos-stack
T0=$(date +%s)
at() { echo "$1 at $(( $(date +%s) - T0 )) s" | tee -a $OUT/timings.txt; }
left() { echo $(( $1 - ($(date +%s) - T0) )); }
save_logs() {
  tar -czf $OUT/.logs.tmp --exclude logs/paused_state.pt logs results/demonstrations/metaworld/demonstrations.json \
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
SNAKEMAKE="python3 -m snakemake --rerun-triggers mtime input --cores 16 --scheduler greedy --nolock --rerun-incomplete"
mkdir -p logs
if [ ! -f logs/started ]; then  # the first call on this machine: retrain, not reuse the committed checkpoint
  rm -rf checkpoints/pi05_metaworld/policy checkpoints/pi05_metaworld/tokenizer checkpoints/pi05_metaworld/training.json
  touch logs/started
fi
[ -f /tmp/sim/env.sh ] || python3 benchmarks/simstack.py unpack --from $S --target /tmp/sim > logs/unpack.log 2>&1 \
  || { tail -20 logs/unpack.log; exit 1; }
. /tmp/sim/env.sh
export PYTHONPATH=$PWD/src:$PYTHONPATH PYTHONUNBUFFERED=1 MUJOCO_GL=egl
( while sleep 20; do save_logs; done ) &
nvidia-smi -L | tee -a $OUT/timings.txt; at "ready (resume state: $(ls checkpoints/pi05_metaworld/resume 2>/dev/null))"
if [ "$STEPS" = rate ] && [ ! -f logs/step_rate.json ]; then
  phase 150 logs/step_rate.log python3 benchmarks/gpu_train_step.py --out logs/step_rate.json --steps 30 \
    --batches 128 256 --precisions float32 --graphs off on --check-graph-steps 8
  at "step rate (rc $?)"; grep '^{' logs/step_rate.log
fi
if [ ! -f results/demonstrations/metaworld/manifest.tsv ]; then
  phase "${DEMOS_LIMIT_S:-420}" logs/snakemake_demonstrations.log $SNAKEMAKE results/demonstrations/metaworld/manifest.tsv \
    --configfile config/trained_study.yaml
  at "demonstrations (rc $?)"; grep "episodes kept\|episodes tried" logs/demonstrations/metaworld.log | tail -2
  [ -f results/demonstrations/metaworld/manifest.tsv ] || { tail -30 logs/demonstrations/metaworld.log; exit 1; }
fi
# Loading the dataset onto the device and saving the state take about 40 s of a training call.
if [ ! -f logs/sized.yaml ]; then
  python3 - "$(left $(( TRAIN_END_S - 40 )))" "$SECOND_CALL_TRAIN_S" "$STEPS" > logs/sized.yaml <<'PY' || exit 1
import json, sys, yaml
this_call, second_call = float(sys.argv[1]), float(sys.argv[2])
if sys.argv[3] == "config" or sys.argv[3].isdigit():  # the config's recipe, or it with STEPS steps
    training = yaml.safe_load(open("config/trained_study.yaml"))["training"]
    if sys.argv[3].isdigit():
        training["steps"] = training["policy"]["decay_steps"] = int(sys.argv[3])
    print(yaml.safe_dump({"training": training}))
    sys.exit()
record = json.load(open("logs/step_rate.json"))
graph_ok = (record.get("graph_check") or {}).get("max_rel_loss_diff", 1) < 1e-3  # the captured step only if checked
rows = [r for r in record["variants"] if graph_ok or not r["cuda_graph"]]
best = {b: max((r for r in rows if r["batch_size"] == b), key=lambda r: r["samples_per_s"]) for b in {r["batch_size"] for r in rows}}
# a larger batch only when it gives 1.4x the samples a second of the smaller (more steps otherwise)
pick = best[min(best)]
for batch in sorted(best):
    pick = best[batch] if best[batch]["samples_per_s"] >= 1.4 * pick["samples_per_s"] else pick
steps = int(0.92 * pick["steps_per_s"] * (this_call - pick["first_5_steps_s"] + second_call))
training = yaml.safe_load(open("config/trained_study.yaml"))["training"]
training.update(steps=steps, batch_size=pick["batch_size"], precision=pick["precision"], cuda_graph=pick["cuda_graph"],
                compile_mode=pick["compile_mode"])
training["policy"]["decay_steps"] = steps
print(yaml.safe_dump({"training": training}))
PY
fi
grep -v "^    \|^  policy" logs/sized.yaml
python3 -c "
import sys, yaml; c = yaml.safe_load(open('logs/sized.yaml')); c['training']['time_limit_s'] = max(1, float(sys.argv[1]))
yaml.safe_dump(c, open('logs/this_call.yaml', 'w'))" "$(left $(( TRAIN_END_S - 40 )))"
if [ ! -f checkpoints/pi05_metaworld/training.json ]; then
  phase "$(left $(( TRAIN_END_S + 30 )))" logs/snakemake_training.log $SNAKEMAKE checkpoints/pi05_metaworld/training.json \
    --configfile config/trained_study.yaml logs/this_call.yaml
  at "training (rc $?)"; grep "dataset on\|policy:\|step \|time limit\|stopped" logs/train_policy.log | tail -8
fi
if [ -f checkpoints/pi05_metaworld/resume/state.pt ]; then  # paused: what a lost machine would take with it
  python3 -c "
import torch; s = torch.load('checkpoints/pi05_metaworld/resume/state.pt', map_location='cpu', weights_only=False)
torch.save({k: s[k] for k in ('binding', 'policy', 'step', 'losses', 'wall_s')}, 'logs/paused_state.pt')"
  tar -cf - logs/paused_state.pt results/demonstrations/metaworld/dataset/meta results/demonstrations/metaworld/manifest.tsv \
    | split -b 15M - $OUT/paused.tar.part
  at "paused state exported"
fi
if [ -f checkpoints/pi05_metaworld/training.json ]; then
  tar --exclude resume -cf - checkpoints/pi05_metaworld | split -b 15M - $OUT/ckpt.tar.part
fi
# The closed-loop check only when the call has room for it; otherwise it runs on the CPU from the returned checkpoint
# (benchmarks/trained_policy_closed_loop.py, the same arguments with --device cpu).
if [ -f checkpoints/pi05_metaworld/training.json ] && [ "$(left 585)" -ge "${CLOSED_LOOP_MIN_S:-150}" ]; then
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
