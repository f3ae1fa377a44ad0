#!/usr/bin/env bash
# The GPU study of config/gpu_study.yaml (then its fixed-design reruns, config/gpu_study_fixed.yaml) across device
# calls of at most 9 minutes, each resuming where the previous calls stopped. One call:
#   run(kind="nvidia-h100-x1", timeout_s=600, carry=[".gpuwork/study-stack", ".carry/gpu_study"],
#       command="OUT=$OUT STUDY_END_S=470 bash benchmarks/gpu_study.sh")
# then, here, with the reply's files_at:  bash benchmarks/gpu_study.sh keep FILES_AT
# - .gpuwork/study-stack: the simulator stack, packed here once per session (git-ignored, 22.7 MiB):
#     python benchmarks/simstack.py pack --benchmark metaworld --closed-loop --config config/gpu_study.yaml --out .gpuwork/study-stack
#   unpacked to /tmp/sim on a machine's first call; a later call on the same warm machine may leave it out of `carry`.
#   Everything that travels, tracked files included, must fit 64 MiB: docs/gpu_study.md says what to leave out.
# - .carry/gpu_study: what the next call needs (absent on the first): carry.tgz (the baseline's records, the journals
#   of unfinished cells, progress.tsv: which cells are finished) and calls.tsv. `keep FILES_AT` puts it there and
#   keeps the call's records.tgz.part* in .gpuwork/gpu_study/returned/<time>/ (finished cells stay here, not carried).
# - kind nvidia-h100-x1 on every call: a journal resumes only on a device of the same name and a host of the same
#   CPU model and renderer (runner.journal); a partial cell recorded elsewhere is set aside (returned) and restarted.
# The call: unpack the stack (once per machine); restore .carry/gpu_study (tar keeps the records' times); rewrite the
# checkpoint stamp and date it back (its path is this machine's; a carried record must not be older than it); then
# for each phase of PHASES (the live study, then the fixed reruns) Snakemake runs the unfinished cells only (the
# calibrations of finished cells are not carried: redoing one would rerun every cell reading it), each cell resuming
# its journal (runner.journal). At STUDY_END_S seconds into the call (or when the file STOP_FILE appears) Snakemake's
# process group gets SIGTERM: each rollout ends as on Ctrl-C (runner.signals), its journal holding every finished
# episode and no partial one (an episode cut off reruns whole next time: its outcome depends on its task, variation
# and seed alone); SIGKILL after GRACE_S.
# $OUT gets (8 files at most, under 64 MiB): records.tgz.part* (at most 3 parts of 15 MB: header.json and
# episodes.parquet of every cell finished on this machine, the journals of the unfinished and set-aside ones),
# carry.tgz, calls.tsv (a line per call so far: device, seconds of rollouts, episodes, episodes per hour, episodes in
# all), progress.tsv (every cell: episodes, finished, decision), timings.txt, logs.tar.gz.
# Here, once every cell is finished: `bash benchmarks/gpu_study.sh export` unpacks every kept call's records in
# order and copies each finished cell to results/gpu_study/{live,fixed}/<ref>/ (the layout records_dir reads).
# Across sessions (a session's checkout is lost, .carry/ and .gpuwork/ with it): `save` at a session's end exports
# the cells finished so far and copies the carry (and the calls' lines, the cells' progress) to SAVED, both to be
# committed; `resume` at the next session's start puts the committed carry back into CARRY.
# `plan` lists each phase's cells as the next call sees them (finished or not).
# The precision search (config/gpu_search.yaml, then its confirmation) runs through benchmarks/gpu_search.sh, which
# sets the variables below for it: its own CARRY, SAVED, PROGRESS and EXPORT_DIR; EXPORTS (each phase's finished cells
# exported to a folder of its own); SEARCH_UNTIL=determined (a phase whose config lists its `search` table stops its
# rollouts once the recorded candidates determine the search, `search-state`, and the call goes on to the next phase).
set -u -o pipefail
CMD=${1:-run}
PYTHON=${PYTHON:-python3}
CARRY=${CARRY:-.carry/gpu_study}
RETURNED=${RETURNED:-.gpuwork/gpu_study/returned}
STACK=${STACK:-.gpuwork/study-stack}
SAVED=${SAVED:-results/gpu_study/carry}  # committed: the carry between sessions
STUDY_END_S=${STUDY_END_S:-470}  # seconds into this call at which the rollouts are stopped
GRACE_S=${GRACE_S:-45}  # after SIGTERM: the cells close their workers and journals, then SIGKILL
STOP_FILE=${STOP_FILE:-}  # if set, its appearance stops the rollouts as the deadline does
CORES=${CORES:-$(nproc)}
# Phases, separated by ';': each the config files of one `snakemake --configfile` (merged over config/config.yaml).
# A phase naming a file that does not exist (the search's tables/search_chosen.yaml before the search has chosen) is
# skipped.
PHASES=${PHASES:-"config/gpu_study.yaml;config/gpu_study.yaml config/gpu_study_fixed.yaml"}
export PHASES
export PROGRESS=${PROGRESS:-results/gpu_study_progress.tsv}  # every cell's row (carried), as progress.tsv returns it
export EXPORT_DIR=${EXPORT_DIR:-results/gpu_study}  # `export`: the finished cells, by reference, under <kind>/
# `export` kinds: unset, a cell goes to live/ (under a stopping rule) or fixed/ (in full), the baseline to both; set
# (one folder name per phase, separated by ';'), each cell goes to the folder of every phase whose cells hold it.
export EXPORTS=${EXPORTS:-}
# determined: a phase whose config lists its `search` table ends once the recorded candidates determine the search
# (`search-state` writes tables/search_chosen.yaml) and the call goes on to the next phase; empty: run every cell.
SEARCH_UNTIL=${SEARCH_UNTIL:-}
PART_BYTES=15000000
MAX_PARTS=3  # with carry.tgz, calls.tsv, progress.tsv, timings.txt and logs.tar.gz: 8 files
T0=$(date +%s)
export PYTHONPATH=$PWD/src${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-egl}
mkdir -p logs

# The cells' bookkeeping, in Python (the workflow's own cell hashing). PROGRESS holds a row per cell: the carried
# rows of cells finished elsewhere, updated from the cell folders here (`progress`). `cells CONFIGS`: the cells of a
# phase (hash, ref, finished); `stamp CONFIGS`: the checkpoint stamp's path; `check-hosts`: set aside unfinished cells
# recorded on another host or device; `files` / `carry-files`: what the records / the carry hold; `export`: copy
# finished cells to EXPORT_DIR; `search-state CONFIGS`: whether the search of the phase is determined (exit 0, and
# tables/search_chosen.yaml names its choice), not yet (10) or the phase runs no search (11).
HELPER='
import csv, json, os, shutil, sys, time
from pathlib import Path

CELLS, ASIDE, PROGRESS = Path("results/cells"), Path("results/cells_set_aside"), Path(os.environ["PROGRESS"])
CHOSEN = Path("tables/search_chosen.yaml")
COLUMNS = ["hash", "ref", "preset", "sequential", "episodes", "finished", "decision"]


def merged(configs):
    from vlaquantbench.config import _merge, _parse, validate
    raw = _parse(Path("config/config.yaml"))
    for path in configs:
        raw = _merge(raw, _parse(Path(path)))
    return validate(raw, "config", " ".join(configs))


def study_cells(configs):
    from vlaquantbench.workflow import WorkflowConfig
    return WorkflowConfig.from_snakemake(merged(configs), Path(".")).study_cells()


def search_state(configs):
    """The search of the phase decided from the live rule of each finished candidate (the decision in its header, the
    carried progress rows of cells finished in earlier calls): 0 when the finished candidates determine it (its
    chosen cell into CHOSEN, none chosen: CHOSEN removed), 10 when the search would read a candidate not finished
    yet, 11 when the phase runs no search. tables/search.csv re-derives it from the records, here."""
    from vlaquantbench.search import Candidate, SearchDesign, SearchUndetermined, Verdict, precision_search
    from vlaquantbench.tables.search import allocation_config
    from vlaquantbench.workflow import WorkflowConfig
    raw = merged(configs)
    search = raw.get("search")
    if not search or search["table"] not in raw.get("tables", []):
        return 11
    workflow = WorkflowConfig.from_snakemake(raw, Path("."))
    baseline, space = workflow.search_space()
    cells = {cfg["ref"]: (key, cfg) for key, cfg in workflow.study_cells().items()}
    rows = progress()
    done = {ref: rows[cells[ref][0]] for ref in space if str(rows.get(cells[ref][0], {}).get("finished", 0)) == "1"
            and rows[cells[ref][0]]["decision"]}
    cap = {ref: cfg["episodes_per_task"] * len(cfg["tasks"]) for ref, (_, cfg) in cells.items()}
    design = SearchDesign(search.get("alpha", 0.05), search.get("margin_pp", 5.0))
    candidates = [Candidate.from_ref(ref) for ref in space if ref != baseline]
    decide = lambda c, _: Verdict(done[c.ref]["decision"], int(done[c.ref]["episodes"]), cap[c.ref])
    try:
        result = precision_search(candidates, decide, design, [c.ref for c in candidates if c.ref not in done])
    except SearchUndetermined as err:
        print(f"search: not determined yet: {err}")
        return 10
    chosen = result.chosen.ref if result.chosen else None
    lines = [f"{design.guarantee(len(result.order))}.", "chosen: " + (chosen or "none"),
             f"episodes: {result.episodes_spent} read by the search ({len(result.verdicts)} visited, "
             f"{len(result.pruned_by)} pruned), of {len(result.order)} x {max(cap.values())} in full",
             "decided on the device from each finished candidate and its live decision (benchmarks/gpu_study.sh "
             "search-state); tables/search.csv re-derives it from the records"]
    print("search: determined: " + "; ".join(lines[1:3]))
    if chosen is None:
        CHOSEN.unlink(missing_ok=True)
    else:
        CHOSEN.parent.mkdir(parents=True, exist_ok=True)
        CHOSEN.write_text(allocation_config(search.get("allocation", "search"), chosen, baseline.rsplit("/", 1)[0], lines))
    return 0


def finished(folder):
    return (folder / "episodes.parquet").is_file() and (folder / "header.json").is_file()


def header(folder):
    if (folder / "header.json").is_file():
        return json.loads((folder / "header.json").read_text())
    with open(folder / "journal.jsonl") as handle:
        return json.loads(handle.readline())


def episodes(folder):
    if finished(folder):
        import pandas as pd
        return len(pd.read_parquet(folder / "episodes.parquet", columns=["episode"]))
    from vlaquantbench.runner.journal import recorded_episodes
    return recorded_episodes(folder / "journal.jsonl")


def progress():
    rows = {}
    if PROGRESS.is_file():
        rows = {row["hash"]: row for row in csv.DictReader(PROGRESS.open(), delimiter="\t")}
    for folder in sorted(p for p in CELLS.glob("*") if (p / "journal.jsonl").is_file() or finished(p)):
        cell, done = header(folder), finished(folder)
        rows[folder.name] = {"hash": folder.name, "ref": cell["ref"], "preset": cell["preset"],
                             "sequential": int(bool(cell["config"].get("sequential"))), "episodes": episodes(folder),
                             "finished": int(done),
                             "decision": (cell.get("stopping") or {}).get("decision", "") if done else ""}
    return rows


command, args = sys.argv[1], sys.argv[2:]
if command == "cells":
    rows = progress()
    for key, cfg in study_cells(args).items():
        print(key, cfg["ref"], int(str(rows.get(key, {}).get("finished", 0)) == "1"))
elif command == "stamp":
    from vlaquantbench.cells import checkpoint_key
    print(f"results/checkpoints/{checkpoint_key(next(iter(study_cells(args).values())))}/checkpoint.json")
elif command == "progress":
    rows = progress()
    text = "\t".join(COLUMNS) + "\n" + "".join("\t".join(str(row[c]) for c in COLUMNS) + "\n" for row in rows.values())
    for path in [PROGRESS, *map(Path, args)]:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
elif command == "count":
    print(sum(int(row["episodes"]) for row in progress().values()))
elif command == "check-hosts":
    from vlaquantbench.runner.gpus import listed_gpus
    from vlaquantbench.runner.provenance import host
    here = {k: v for k, v in host().items() if k != "gpus"}
    names = {g.name for g in listed_gpus() or []}
    for folder in sorted(p for p in CELLS.glob("*") if (p / "journal.jsonl").is_file() and not finished(p)):
        cell = header(folder)
        recorded = {k: v for k, v in (cell.get("host") or here).items() if k != "gpus"}
        device = (cell.get("device") or {}).get("name")
        if recorded != here or (device is not None and device not in names):
            aside = ASIDE / f"{folder.name}-{int(time.time())}"
            aside.parent.mkdir(parents=True, exist_ok=True)
            shutil.move(str(folder), aside)
            ref = cell["ref"]
            print(f"set aside {folder.name} ({ref}): recorded on {recorded} {device}, this machine is {here} "
                  f"{sorted(names)}; the cell restarts here (its journal returns in {aside})")
elif command == "search-state":
    sys.exit(search_state(args))
elif command in ("files", "carry-files"):
    for folder in sorted(p for p in CELLS.glob("*") if p.is_dir()):
        if finished(folder) and (command == "files" or header(folder)["preset"] == "BASELINE"):
            print(folder / "header.json", folder / "episodes.parquet", sep="\n")
        elif not finished(folder) and (folder / "journal.jsonl").is_file():
            print(folder / "journal.jsonl")
    for path in sorted(ASIDE.glob("*/journal.jsonl")) if command == "files" else [PROGRESS]:
        print(path)
    if command == "files" and CHOSEN.is_file():  # `export` reads the later phases of a search with it
        print(CHOSEN)
elif command == "export":
    phases = {}  # EXPORTS: the folder of each phase, for each of its cells
    if os.environ["EXPORTS"]:
        for configs, kind in zip(os.environ["PHASES"].split(";"), os.environ["EXPORTS"].split(";"), strict=True):
            try:  # a later phase of a search needs the tables/search_chosen.yaml returned with the records
                keys = study_cells(configs.split()) if all(Path(c).is_file() for c in configs.split()) else {}
            except Exception as err:
                print(f"phase {configs}: its cells cannot be named here ({err}): none exported to {kind}/")
                keys = {}
            for key in keys:
                phases.setdefault(key, []).extend([kind] if kind not in phases.get(key, []) else [])
    for folder in sorted(p for p in CELLS.glob("*") if finished(p)):
        cell = header(folder)
        if os.environ["EXPORTS"]:
            kinds = phases.get(folder.name, [])
            if not kinds:
                print("not exported:", cell["ref"], f"({folder.name}) is a cell of no phase")
        else:
            kinds = ["live", "fixed"] if cell["preset"] == "BASELINE" else ["live" if cell["config"].get("sequential") else "fixed"]
        for kind in kinds:
            target = Path(os.environ["EXPORT_DIR"]) / kind / cell["ref"]
            target.mkdir(parents=True, exist_ok=True)
            for name in ("header.json", "episodes.parquet"):
                shutil.copy2(folder / name, target / name)
            print(kind, cell["ref"])
'
helper() { "$PYTHON" -c "$HELPER" "$@"; }
at() { echo "$(date -u +%FT%TZ) +$(( $(date +%s) - T0 )) s: $*" | tee -a "${OUT:-logs}/timings.txt"; }

restore() {  # the carry of the last call, the records' times kept
  if [ -f "$CARRY/carry.tgz" ]; then
    tar -xzf "$CARRY/carry.tgz" || { echo "restore: $CARRY/carry.tgz is not a whole tar" >&2; return 1; }
    echo "restored from $CARRY: $(grep -c $'\t1\t[a-z_]*$' "$PROGRESS") finished cell(s)," \
      "$(ls results/cells/*/journal.jsonl 2>/dev/null | wc -l) journal(s)"
  else
    echo "restore: nothing in $CARRY (a first call)"
  fi
  if [ -f "$CARRY/calls.tsv" ]; then cp "$CARRY/calls.tsv" logs/calls.tsv; fi
}

pack() {  # the records into at most MAX_PARTS parts, and the next call's carry
  helper progress "$OUT/progress.tsv" || return 1
  local stage size
  stage=$(mktemp -d)
  helper files > "$stage/files" && tar -czf "$stage/records.tgz" -T "$stage/files" || return 1
  size=$(stat -c %s "$stage/records.tgz")
  if [ "$size" -gt $(( PART_BYTES * MAX_PARTS )) ]; then
    echo "pack: records.tgz is $size bytes, more than $MAX_PARTS parts of $PART_BYTES" >&2; return 1
  fi
  rm -f "$OUT"/records.tgz.part*
  split -b "$PART_BYTES" -d -a 1 "$stage/records.tgz" "$OUT/records.tgz.part"
  helper carry-files > "$stage/carry" && tar -czf "$OUT/carry.tgz" -T "$stage/carry" || return 1
  rm -rf "$stage"
  [ -f logs/calls.tsv ] && cp logs/calls.tsv "$OUT/calls.tsv"
  echo "packed the records ($size bytes) into $(ls "$OUT"/records.tgz.part* | wc -l) part(s), the carry into" \
    "$(stat -c %s "$OUT/carry.tgz") bytes"
}

keep() {  # here, after a call: its carry for the next call, its records kept
  local from=${1:?keep FILES_AT: the folder of the files of the call}
  [ -f "$from/carry.tgz" ] || { echo "keep: $from holds no carry.tgz" >&2; return 1; }
  rm -rf "$CARRY" && mkdir -p "$CARRY" && cp "$from/carry.tgz" "$from/calls.tsv" "$CARRY/" || return 1
  local kept
  kept="$RETURNED/$(date -u +%Y%m%dT%H%M%S%N)"
  mkdir -p "$kept" && cp "$from"/records.tgz.part* "$from/progress.tsv" "$from/timings.txt" "$kept/" || return 1
  echo "kept $from: the carry in $CARRY, the records in $kept"
  tail -1 "$from/calls.tsv"
}

export_records() {  # here: every kept call's records, in order, then the layout to commit
  local call parts
  for call in $(ls -d "$RETURNED"/*/ 2>/dev/null | sort); do
    parts=("$call"records.tgz.part*)
    cat "${parts[@]}" | tar -xzf - || { echo "export: $call's parts are not a whole tar" >&2; return 1; }
  done
  helper export
}

save() {  # here, at a session's end: finished cells exported, the carry into SAVED (commit both)
  [ -f "$CARRY/carry.tgz" ] || { echo "save: $CARRY holds no carry.tgz" >&2; return 1; }
  export_records || return 1
  mkdir -p "$SAVED" && cp "$CARRY/carry.tgz" "$CARRY/calls.tsv" "$SAVED/" \
    && tar -xzf "$CARRY/carry.tgz" -O "$PROGRESS" > "$SAVED/progress.tsv" || return 1
  echo "saved: the carry in $SAVED; $(awk -F'\t' 'NR > 1 && $6 == 1' "$SAVED/progress.tsv" | wc -l) cell(s) finished," \
    "$(tail -1 "$SAVED/calls.tsv" | cut -f6) episodes recorded in all"
}

resume() {  # here, at a session's start: the committed carry back where the calls read it
  [ -f "$SAVED/carry.tgz" ] || { echo "resume: $SAVED holds no carry.tgz (nothing saved: a first call)" >&2; return 1; }
  [ ! -f "$CARRY/carry.tgz" ] || { echo "resume: $CARRY already holds a carry; remove it to resume from $SAVED" >&2; return 1; }
  mkdir -p "$CARRY" && cp "$SAVED/carry.tgz" "$SAVED/calls.tsv" "$CARRY/" && echo "resumed: $CARRY from $SAVED"
}

# phase CONFIGS...: Snakemake on the phase's unfinished cells, in a process group of its own, stopped at the deadline
# (the call ends) or, with SEARCH_UNTIL=determined, once its search is determined (the call goes on).
phase() {
  local config
  for config in "$@"; do
    if [ ! -f "$config" ]; then
      at "phase $*: skipped, $config does not exist (a search not determined yet, or one that chose nothing)"
      return 0
    fi
  done
  local searching=""
  if [ "$SEARCH_UNTIL" = determined ]; then
    helper search-state "$@" >> "${OUT:-logs}/timings.txt" 2>&1
    case $? in
      0) at "phase $*: the search is determined: $(grep '^search: ' "${OUT:-logs}/timings.txt" | tail -1)"; return 0 ;;
      10) searching=1 ;;
    esac
  fi
  local targets
  targets=$(helper cells "$@" | awk '$3 == 0 {print "results/cells/" $1 "/episodes.parquet"}')
  if [ -z "$targets" ]; then at "phase $*: every cell finished"; return 0; fi
  at "phase $*: $(echo "$targets" | wc -l) cell(s) to run${searching:+, until the search is determined}"
  # One --configfile with every file: Snakemake 9 keeps only the last of several --configfile flags.
  setsid "$PYTHON" -m snakemake $targets --configfile "$@" --cores "$CORES" --scheduler greedy --keep-going \
    --rerun-triggers mtime --rerun-incomplete --nolock --resources mem_mb=100000000 > logs/snakemake_phase.log 2>&1 &
  local pid=$! reason="" seen=-1 count
  while kill -0 "$pid" 2>/dev/null; do
    if [ $(( $(date +%s) - T0 )) -ge "$STUDY_END_S" ]; then reason="deadline"; fi
    if [ -n "$STOP_FILE" ] && [ -e "$STOP_FILE" ]; then reason="stop file"; fi
    if [ -z "$reason" ] && [ -n "$searching" ]; then  # a cell finished: is the search determined now?
      # a finished cell's episodes.parquet and header.json, each counted as it appears
      count=$(( $(compgen -G "results/cells/*/episodes.parquet" | wc -l) + $(compgen -G "results/cells/*/header.json" | wc -l) ))
      if [ "$count" != "$seen" ]; then
        seen=$count
        if helper search-state "$@" >> "${OUT:-logs}/timings.txt" 2>&1; then reason="search determined"; fi
      fi
    fi
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
  grep -h "vqb rollout: \|Error in rule\|The run stopped because" logs/snakemake_phase.log | tail -20
  at "phase $* ended (rc $rc${reason:+, $reason})"
  [ -z "$reason" ] || [ "$reason" = "search determined" ]  # a phase stopped by the deadline ends the call
}

case "$CMD" in
  restore) restore; exit $? ;;
  check-hosts) helper check-hosts; exit $? ;;
  keep) keep "${2:-}"; exit $? ;;
  export) export_records; exit $? ;;
  save) save; exit $? ;;
  resume) resume; exit $? ;;
  plan) restore > /dev/null && IFS=';' read -r -a phases <<< "$PHASES" || exit 1
        for configs in "${phases[@]}"; do
          echo "phase $configs:"
          missing=$(for c in $configs; do [ -f "$c" ] || echo "$c"; done)
          if [ -n "$missing" ]; then echo "  skipped: $missing does not exist"; continue; fi
          if [ "$SEARCH_UNTIL" = determined ]; then helper search-state $configs; fi
          helper cells $configs || exit 1
        done; exit 0 ;;
  search-state) helper search-state "${@:2}"; exit $? ;;
  pack) : "${OUT:?OUT: the folder to pack into}"; pack; exit $? ;;
  run) : "${OUT:?OUT: the folder whose files come back}" ;;
  *) echo "usage: [OUT=DIR] bash benchmarks/gpu_study.sh [run|keep FILES_AT|save|resume|export|plan|restore|check-hosts|pack|search-state CONFIGS]" >&2; exit 2 ;;
esac

gpu=$(nvidia-smi -L 2>/dev/null | head -1)
at "start on ${gpu:-no GPU (nvidia-smi lists none)}, $CORES cores"
if [ -d "$STACK" ] && [ ! -f /tmp/sim/env.sh ]; then
  "$PYTHON" benchmarks/simstack.py unpack --from "$STACK" --target /tmp/sim > logs/unpack.log 2>&1 \
    || { tail -20 logs/unpack.log; exit 1; }
fi
if [ -f /tmp/sim/env.sh ]; then . /tmp/sim/env.sh; export PYTHONPATH=$PWD/src:$PYTHONPATH; fi
{ restore && helper check-hosts; } 2>&1 | tee -a "$OUT/timings.txt" || exit 1
before=$(helper count) || exit 1
at "ready: $before episodes recorded before this call"
IFS=';' read -r -a phases <<< "$PHASES"
if compgen -G "results/cells/*/*" > /dev/null; then
  stamp=$(helper stamp ${phases[0]}) || exit 1
  "$PYTHON" -m snakemake "$stamp" --configfile ${phases[0]} --cores 1 --nolock \
    --forcerun download_checkpoint > logs/snakemake_stamp.log 2>&1 || { tail -30 logs/snakemake_stamp.log; exit 1; }
  touch -d "2000-01-01 00:00:00" "$stamp"
  at "checkpoint stamp rewritten and dated back: $stamp"
fi
start_runs=$(date +%s)
for configs in "${phases[@]}"; do
  phase $configs || break
done
run_s=$(( $(date +%s) - start_runs ))
after=$(helper count)
device=$(nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null | head -1)
[ -f logs/calls.tsv ] || printf 'call_start_utc\tdevice\trollout_s\tepisodes\tepisodes_per_hour\ttotal_episodes\n' > logs/calls.tsv
rate=$(awk -v n=$(( after - before )) -v s="$run_s" 'BEGIN { printf "%.0f", (s > 0 ? 3600 * n / s : 0) }')
printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$(date -u -d @"$T0" +%FT%TZ)" "${device:-cpu}" "$run_s" $(( after - before )) \
  "$rate" "$after" >> logs/calls.tsv
at "episodes this call: $(( after - before )) in $run_s s of rollouts ($rate episodes/h); $after recorded in all"
pack 2>&1 | tee -a "$OUT/timings.txt"
tar -czf "$OUT/logs.tar.gz" logs .snakemake/log 2>/dev/null
at done
