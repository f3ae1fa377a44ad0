#!/usr/bin/env bash
# The GPU study of config/gpu_study.yaml (then its fixed-design reruns, config/gpu_study_fixed.yaml) across device
# calls of at most 9 minutes, each resuming from the records the previous calls returned. One call:
#   run(kind="nvidia-h100-x1", timeout_s=600, carry=[".gpuwork/study-stack", ".carry/gpu_study"],
#       command="OUT=$OUT STUDY_END_S=470 bash benchmarks/gpu_study.sh")
# - .gpuwork/study-stack: the simulator stack, packed here once per session (it is git-ignored):
#     python benchmarks/simstack.py pack --benchmark metaworld --closed-loop --config config/gpu_study.yaml --out .gpuwork/study-stack
#   unpacked to /tmp/sim on the machine's first call and reused while the machine stays warm (a later call on the
#   warm machine may leave it out of `carry`). Everything that travels, tracked files included, must fit 64 MiB:
#   the checkpoint (checkpoints/pi05_metaworld) must travel; see docs/gpu_study.md for what to leave out.
# - .carry/gpu_study: what earlier calls returned (their $OUT's records.tgz.part* files), absent on the first call.
#   After each call, here:  rm -rf .carry/gpu_study && mkdir -p .carry/gpu_study &&
#                           cp <files_at>/records.tgz.part* <files_at>/calls.tsv .carry/gpu_study/
# - kind nvidia-h100-x1 on every call: a journal resumes only on a device of the same name and a host of the same
#   CPU model and renderer (runner.journal); a partial cell recorded elsewhere is set aside and restarted here.
# The call: unpack the stack (once per machine); restore the records (tar keeps their times, so a finished cell
# is not rerun); refresh the checkpoint stamp (dated back: it is this machine's); then for each phase of PHASES
# (the live study, then the fixed reruns) Snakemake runs the cells not finished yet, each cell's own folder and
# journal (runner.journal) resuming where the last call stopped. At STUDY_END_S seconds into the call (or when
# the file STOP_FILE appears) Snakemake's process group gets SIGTERM: each rollout ends as on Ctrl-C
# (runner.signals), its journal holding every finished episode and no partial one (an episode cut off reruns
# whole next time: its outcome depends on its task, episode and seed alone), then SIGKILL after GRACE_S.
# $OUT gets: records.tgz.part* (at most 4 parts of 15 MB: results/cells/<hash>/ header, episodes and the
# journals of unfinished cells; results/gpu_study/{live,fixed}/<ref>/ of every finished cell, the layout to
# commit), calls.tsv (one line per call so far: device, seconds, episodes, episodes per hour), progress.tsv
# (every cell: episodes, finished, stopping decision), timings.txt, logs.tar.gz.
# Subcommands `restore` and `pack` run those steps alone (tests/test_gpu_study.py); `run` (default) all.
set -u -o pipefail
CMD=${1:-run}
PYTHON=${PYTHON:-python3}
CARRY=${CARRY:-.carry/gpu_study}
STACK=${STACK:-.gpuwork/study-stack}
STUDY_END_S=${STUDY_END_S:-470}  # seconds into this call at which the rollouts are stopped
GRACE_S=${GRACE_S:-45}  # after SIGTERM: the cells close their workers and journals, then SIGKILL
STOP_FILE=${STOP_FILE:-}  # if set, its appearance stops the rollouts as the deadline does
CORES=${CORES:-$(nproc)}
# Phases, separated by ';': each the config files of one `snakemake --configfile` (merged over config/config.yaml).
PHASES=${PHASES:-"config/gpu_study.yaml;config/gpu_study.yaml config/gpu_study_fixed.yaml"}
PART_BYTES=15000000
MAX_PARTS=4  # with calls.tsv, progress.tsv, timings.txt and logs.tar.gz: 8 files, under 64 MiB
T0=$(date +%s)
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-egl}
mkdir -p logs

# The cells' bookkeeping, in Python (the workflow's own cell hashing): `cells CONFIGS` lists the cells of a phase
# (hash, ref, finished or not); `check-hosts` sets aside unfinished cells recorded on another host or device;
# `stamp CONFIGS` prints the checkpoint stamp's path; `export` copies finished cells to results/gpu_study/;
# `count` sums the episodes recorded; `progress` writes progress.tsv.
HELPER='
import json, shutil, sys, time
from pathlib import Path

CELLS = Path("results/cells")


def merged(configs):
    from vlaquantbench.config import _merge, _parse, validate
    raw = _parse(Path("config/config.yaml"))
    for path in configs:
        raw = _merge(raw, _parse(Path(path)))
    return validate(raw, "config", " ".join(configs))


def study_cells(configs):
    from vlaquantbench.workflow import WorkflowConfig
    return WorkflowConfig.from_snakemake(merged(configs), Path(".")).study_cells()


def journal_header(folder):
    with open(folder / "journal.jsonl") as handle:
        return json.loads(handle.readline())


def episodes(folder):
    from vlaquantbench.runner.journal import recorded_episodes
    if (folder / "episodes.parquet").is_file():
        import pandas as pd
        return len(pd.read_parquet(folder / "episodes.parquet", columns=["episode"]))
    return recorded_episodes(folder / "journal.jsonl")


command, args = sys.argv[1], sys.argv[2:]
if command == "cells":
    for key, cfg in study_cells(args).items():
        print(key, cfg["ref"], int((CELLS / key / "episodes.parquet").is_file()))
elif command == "stamp":
    from vlaquantbench.cells import checkpoint_key
    cfg = next(iter(study_cells(args).values()))
    print(f"results/checkpoints/{checkpoint_key(cfg)}/checkpoint.json")
elif command == "check-hosts":
    from vlaquantbench.runner.gpus import listed_gpus
    from vlaquantbench.runner.provenance import host
    here = {k: v for k, v in host().items() if k != "gpus"}
    names = {g.name for g in listed_gpus() or []}
    for journal in sorted(CELLS.glob("*/journal.jsonl")):
        folder = journal.parent
        if (folder / "episodes.parquet").is_file():
            continue
        header = journal_header(folder)
        recorded = {k: v for k, v in (header.get("host") or here).items() if k != "gpus"}
        device = (header.get("device") or {}).get("name")
        if recorded != here or (device is not None and device not in names):
            aside = Path("results/cells_set_aside") / f"{folder.name}-{int(time.time())}"
            aside.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(folder), aside)
            ref = header.get("ref")
            print(f"set aside {folder.name} ({ref}): recorded on {recorded} {device}, this machine "
                  f"is {here} {sorted(names)}; the cell restarts here (its episodes kept in {aside})")
elif command == "export":
    for header in sorted(CELLS.glob("*/header.json")):
        if not (header.parent / "episodes.parquet").is_file():
            continue
        cell = json.loads(header.read_text())
        kinds = ["live", "fixed"] if cell["preset"] == "BASELINE" else ["live" if cell["config"].get("sequential") else "fixed"]
        for kind in kinds:
            folder = Path("results/gpu_study") / kind / cell["ref"]
            folder.mkdir(parents=True, exist_ok=True)
            for name in ("header.json", "episodes.parquet"):
                shutil.copy2(header.parent / name, folder / name)
elif command == "count":
    print(sum(episodes(folder) for folder in CELLS.glob("*") if (folder / "journal.jsonl").is_file()
              or (folder / "episodes.parquet").is_file()))
elif command == "progress":
    rows = ["\t".join(["hash", "ref", "sequential", "episodes", "finished", "decision"])]
    for folder in sorted(p for p in CELLS.glob("*") if p.is_dir()):
        if (folder / "header.json").is_file():
            header = json.loads((folder / "header.json").read_text())
        elif (folder / "journal.jsonl").is_file():
            header = journal_header(folder)
        else:
            continue
        done = (folder / "episodes.parquet").is_file()
        decision = (header.get("stopping") or {}).get("decision", "") if done else ""
        fields = [folder.name, header["ref"], int(bool(header["config"].get("sequential"))), episodes(folder), int(done), decision]
        rows.append("\t".join(map(str, fields)))
    Path(args[0]).write_text("\n".join(rows) + "\n")
'
helper() { "$PYTHON" -c "$HELPER" "$@"; }
at() { echo "$(date -u +%FT%TZ) +$(( $(date +%s) - T0 )) s: $*" | tee -a "${OUT:-logs}/timings.txt"; }

restore() {  # the records of earlier calls, with their modification times
  local parts=("$CARRY"/records.tgz.part*)
  if [ -e "${parts[0]}" ]; then
    cat "${parts[@]}" | tar -xzf - || { echo "restore: $CARRY's parts do not make a whole tar" >&2; return 1; }
    echo "restored $(ls -d results/cells/*/ 2>/dev/null | wc -l) cell folders from ${#parts[@]} part(s) in $CARRY"
  else
    echo "restore: no records in $CARRY (a first call)"
  fi
  [ -f "$CARRY/calls.tsv" ] && cp "$CARRY/calls.tsv" logs/calls.tsv
  helper check-hosts
}

pack() {  # finished cells whole, unfinished ones with their journals, into at most MAX_PARTS parts
  helper export && helper progress "$OUT/progress.tsv" || return 1
  local stage
  stage=$(mktemp -d)
  tar -czf "$stage/records.tgz" --exclude=writer.lock $(ls -d results/cells results/cells_set_aside results/gpu_study \
    2>/dev/null) || return 1
  local size
  size=$(stat -c %s "$stage/records.tgz")
  if [ "$size" -gt $(( PART_BYTES * MAX_PARTS )) ]; then
    echo "pack: records.tar is $size bytes, more than $MAX_PARTS parts of $PART_BYTES" >&2; return 1
  fi
  rm -f "$OUT"/records.tgz.part*
  split -b "$PART_BYTES" -d -a 1 "$stage/records.tgz" "$OUT/records.tgz.part"
  rm -rf "$stage"
  [ -f logs/calls.tsv ] && cp logs/calls.tsv "$OUT/calls.tsv"
  echo "packed $size bytes into $(ls "$OUT"/records.tgz.part* | wc -l) part(s)"
}

# phase CONFIGS...: Snakemake on the phase's unfinished cells, in a process group of its own, stopped at the deadline.
phase() {
  local targets
  targets=$(helper cells "$@" | awk '$3 == 0 {print "results/cells/" $1 "/episodes.parquet"}')
  if [ -z "$targets" ]; then at "phase $*: every cell finished"; return 0; fi
  at "phase $*: $(echo "$targets" | wc -l) cell(s) to run"
  local config_args=()
  for config in "$@"; do config_args+=(--configfile "$config"); done
  # Only the unfinished cells are targets (no table: the calibrations of finished cells are not carried, and a
  # calibration to redo would rerun every cell reading it); mtime alone decides reruns (no metadata is carried).
  setsid "$PYTHON" -m snakemake $targets "${config_args[@]}" --cores "$CORES" --scheduler greedy --keep-going \
    --rerun-triggers mtime --rerun-incomplete --nolock --resources mem_mb=100000000 > "logs/snakemake_phase.log" 2>&1 &
  local pid=$! reason=""
  while kill -0 "$pid" 2>/dev/null; do
    if [ $(( $(date +%s) - T0 )) -ge "$STUDY_END_S" ]; then reason="deadline"; fi
    if [ -n "$STOP_FILE" ] && [ -e "$STOP_FILE" ]; then reason="stop file"; fi
    if [ -n "$reason" ]; then
      at "stopping the rollouts ($reason): SIGTERM"
      kill -TERM -- -"$pid" 2>/dev/null
      local waited=0
      while kill -0 "$pid" 2>/dev/null && [ "$waited" -lt "$GRACE_S" ]; do sleep 1; waited=$(( waited + 1 )); done
      kill -KILL -- -"$pid" 2>/dev/null
      break
    fi
    sleep 2
  done
  wait "$pid"; local rc=$?
  cat logs/snakemake_phase.log >> logs/snakemake.log
  grep -h "vqb rollout: \|Error in rule\|The run stopped because\|set aside" logs/snakemake_phase.log | tail -20
  at "phase $* ended (rc $rc${reason:+, $reason})"
  [ -z "$reason" ]  # a stopped phase ends the call
}

case "$CMD" in
  restore) restore; exit $? ;;
  pack) : "${OUT:?OUT: the folder to pack into}"; pack; exit $? ;;
  run) : "${OUT:?OUT: the folder whose files come back}" ;;
  *) echo "usage: OUT=DIR bash benchmarks/gpu_study.sh [run|restore|pack]" >&2; exit 2 ;;
esac

at "start on $(nvidia-smi -L 2>/dev/null | head -1 || echo 'no nvidia-smi')"
if [ -d "$STACK" ] && [ ! -f /tmp/sim/env.sh ]; then
  "$PYTHON" benchmarks/simstack.py unpack --from "$STACK" --target /tmp/sim > logs/unpack.log 2>&1 \
    || { tail -20 logs/unpack.log; exit 1; }
fi
if [ -f /tmp/sim/env.sh ]; then . /tmp/sim/env.sh; export PYTHONPATH=$PWD/src:$PYTHONPATH; fi
restore 2>&1 | tee -a "$OUT/timings.txt" || exit 1
before=$(helper count)
at "ready: $before episodes recorded before this call"
# The checkpoint stamp names this machine's checkpoint folder: rewritten here, then dated back so that no carried
# record is older than its input (a rerun of every finished cell otherwise).
IFS=';' read -r -a phases <<< "$PHASES"
stamp=$(helper stamp ${phases[0]}) || exit 1
"$PYTHON" -m snakemake "$stamp" $(for c in ${phases[0]}; do echo --configfile "$c"; done) --cores 1 --nolock \
  --forcerun download_checkpoint > logs/snakemake_stamp.log 2>&1 || { tail -30 logs/snakemake_stamp.log; exit 1; }
touch -d "2000-01-01 00:00:00" "$stamp"
start_runs=$(date +%s)
for configs in "${phases[@]}"; do
  phase $configs || break
done
run_s=$(( $(date +%s) - start_runs ))
after=$(helper count)
device=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)
[ -f logs/calls.tsv ] || printf 'call_start_utc\tdevice\trollout_s\tepisodes\tepisodes_per_hour\ttotal_episodes\n' > logs/calls.tsv
rate=$(awk -v n=$(( after - before )) -v s="$run_s" 'BEGIN { printf "%.0f", s > 0 ? 3600 * n / s : 0 }')
printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$(date -u -d @"$T0" +%FT%TZ)" "${device:-cpu}" "$run_s" $(( after - before )) \
  "$rate" "$after" >> logs/calls.tsv
at "episodes this call: $(( after - before )) in $run_s s of rollouts ($rate episodes/h); $after recorded in all"
pack 2>&1 | tee -a "$OUT/timings.txt"
tar -czf "$OUT/logs.tar.gz" logs .snakemake/log 2>/dev/null
at done
