"""Soak: `kill -9` a running demo cell again and again at seeded random moments, then let it finish;
count lost and duplicated episodes and check the resumed records against an uninterrupted run.

    .venv/bin/python tests/soak_kill9.py --kills 20 --out benchmarks/results/soak_kill9_cpu.json
    .venv/bin/python tests/soak_kill9.py --kills 2 --write-kills 1 --tasks 0 --episodes-per-task 3 \
        --max-steps 10 --window 4 --startup-window 8 --anchor-p 0 0 1  # CI's (tests/test_runner_soak.py)
    .venv/bin/python tests/soak_kill9.py --ref metaworld/metaworld_easy/metaworld_expert/rtn-BASELINE-e2e \
        --max-steps suite --kills 2 --write-kills 1  # Meta-World's scripted experts (tests/test_metaworld_runner.py)

The cell first runs uninterrupted in one folder (the reference), then, in another, through the
kills; when the windows below are given rather than measured on the reference (`--window`, and
`--startup-window` where the startup or running anchor may be drawn), the reference runs beside
the kills instead. Each attempt runs `runner.cell.run_cell` in a fresh process group (the runner
and its LIBERO workers), and a kill is SIGKILL to the whole group. A seeded RNG times the first
`kills - write_kills` kills from one of three anchors, chosen with probabilities `--anchor-p`:

    startup   launch: uniform in the reference's start-up time (policy load and quantization, while
              the LIBERO workers start and build their first envs)
    running   launch + the reference's start-up time (the policy ready, first resets and
              episodes): uniform in `--window` s
    append    the attempt's first new journal line (right after an append, mid-episode of the
              other slots and of the next ones): uniform in `--window` s

`--startup-window` defaults to the reference's start-up time (launch to its journal's header line),
`--window` to half a round of its episodes (a round: its running time over episodes / envs), so
that a kill lands within the episodes in flight. A timed attempt that completes the cell before its
kill is counted, not a kill; once the journal holds every episode, the remaining kills are
write-phase kills (on a machine that gets faster than the reference run, running-anchored kills
also add episodes).

The last `--write-kills` kills land while the records are being written: the soak watches the cell
folder (every `--poll` s) for the atomic writer's temporary files (`.header.json.*.tmp`,
`.episodes.parquet.*.tmp`) and kills the group the moment one appears. The first such attempt runs
the cell's remaining episodes and is killed in its final write; later ones find every episode in
the journal and are killed while they rewrite the records. An attempt whose write ends before the
soak sees it is a miss (counted, not a kill).

A journal append is one `write()` of whole lines, which SIGKILL cannot cut, so `journal_torn` (a
last line without its newline after a kill) is reported rather than expected; tests/
test_runner_journal.py covers a torn line directly.

Reported: kills that landed, per phase; episodes lost (in the uninterrupted run, or journaled by some
attempt, but not in the resumed records) and duplicated (journal lines for an episode already
recorded); whether `episodes.parquet` ever existed while the journal was incomplete, or ever failed
to read as the whole cell; temporary files left behind; and whether every episode's outcome, step
count and action digest, the records (timing columns aside) and the header equal the uninterrupted
run's. Exit status 1 if anything but 0 lost / 0 duplicated / exact resume was measured.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from vlaquantbench.cells import cell_config
from vlaquantbench.errors import UserError
from vlaquantbench.records import read_cell
from vlaquantbench.records.cell import EPISODES_FILE, HEADER_FILE, JOURNAL_FILE
from vlaquantbench.runner.journal import TIMING_FIELDS

RUN_CELL = ("import json, sys; from vlaquantbench.runner.cell import run_cell; "
            "run_cell(json.loads(sys.argv[1]), sys.argv[2], num_envs=int(sys.argv[3]), progress=False)")
TIMING = list(TIMING_FIELDS)  # measured, not outcomes: they differ between any two runs
KEY = ("task_id", "episode", "seed")
ANCHORS = ("startup", "running", "append")
WRITES = (f".{HEADER_FILE}.", f".{EPISODES_FILE}.")  # the atomic writer's temporary files: `.<name>.<...>.tmp`


def journal_lines(folder: Path) -> list[dict]:
    path = folder / JOURNAL_FILE
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_bytes().split(b"\n")[:-1] if line]  # a torn last line is no line


def journal_episodes(folder: Path) -> list[dict]:
    return [r for r in journal_lines(folder) if r["kind"] == "episode"]


def episode_key(record: dict) -> tuple:
    return tuple(record[k] for k in KEY)


def temporary_files(folder: Path) -> list[str]:
    if not folder.is_dir():
        return []
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(WRITES) and p.name.endswith(".tmp"))


def launch(cfg: dict, folder: Path, num_envs: int, stderr=subprocess.DEVNULL) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(folder), str(num_envs)],
                            start_new_session=True, stderr=stderr)


def complete(cfg: dict, folder: Path, num_envs: int) -> dict:
    """Run the cell to the end; its wall time and start-up time (launch to the journal's first line,
    which the runner writes once the policy is loaded and quantized; None if the journal existed)."""
    began = time.monotonic()
    fresh = not (folder / JOURNAL_FILE).exists()
    startup = None
    with tempfile.TemporaryFile() as stderr:
        process = launch(cfg, folder, num_envs, stderr=stderr)
        while process.poll() is None:
            if fresh and startup is None and (folder / JOURNAL_FILE).exists():
                startup = time.monotonic() - began
            time.sleep(0.05)
        if process.returncode:
            stderr.seek(0)
            tail = stderr.read().decode(errors="replace")[-3000:]
            raise RuntimeError(f"the cell in {folder} failed (exit {process.returncode}):\n{tail}")
    return {"total_s": time.monotonic() - began, "startup_s": startup}


def kill_group(process: subprocess.Popen) -> None:
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()


def timed_kill(cfg: dict, folder: Path, args: argparse.Namespace, rng: random.Random) -> dict | None:
    """One attempt killed at a moment the RNG picks after one of the anchors (see the module doc);
    None if the attempt completed the cell first."""
    anchor = rng.choices(ANCHORS, weights=args.anchor_p)[0]
    delay = rng.uniform(0, args.startup_window if anchor == "startup" else args.window)
    launched = time.monotonic()
    lines = len(journal_lines(folder))
    process = launch(cfg, folder, args.num_envs)
    reached = {"startup": lambda: True, "running": lambda: time.monotonic() >= launched + args.startup_window,
               "append": lambda: len(journal_lines(folder)) > lines}[anchor]
    while not reached() and process.poll() is None:
        time.sleep(0.05)
    anchored = time.monotonic()
    time.sleep(delay)
    if process.poll() is not None:
        if process.returncode:
            raise RuntimeError(f"the cell in {folder} failed (exit {process.returncode}) during a timed attempt")
        return None  # the attempt completed the cell before its kill
    kill_group(process)
    now = time.monotonic()
    return {"phase": anchor, "at_s": round(now - launched, 2), "after_anchor_s": round(now - anchored, 2)}


def write_kill(cfg: dict, folder: Path, args: argparse.Namespace) -> dict | None:
    """One attempt killed the moment a temporary file of the record writer appears; None on a miss.
    Files an earlier killed writer left (the next write removes them) do not count."""
    left = set(temporary_files(folder))
    launched = time.monotonic()
    process = launch(cfg, folder, args.num_envs)
    while process.poll() is None:
        if seen := sorted(set(temporary_files(folder)) - left):
            kill_group(process)
            return {"phase": "write", "at_s": round(time.monotonic() - launched, 2), "seen": seen}
        time.sleep(args.poll)
    if process.returncode:
        raise RuntimeError(f"the cell in {folder} failed (exit {process.returncode}) during a write-phase attempt")
    return None


def after_kill(folder: Path) -> dict:
    """What a kill left in the folder: journal progress, torn tail, temporary files, readable records."""
    raw = (folder / JOURNAL_FILE).read_bytes() if (folder / JOURNAL_FILE).exists() else b""
    state = {
        "episodes_journaled": len(journal_episodes(folder)),
        "journal_torn": bool(raw) and not raw.endswith(b"\n"),
        "temporary_files": temporary_files(folder),
        "parquet_present": (folder / EPISODES_FILE).exists(),
    }
    if state["parquet_present"]:
        try:
            state["parquet_rows"] = len(read_cell(folder).episodes)
        except (UserError, OSError, ValueError) as err:  # a half-written record file would land here
            state["parquet_rows"] = None
            state["parquet_error"] = str(err)[:300]
    return state


def soak(cfg: dict, folder: Path, args: argparse.Namespace, episodes: int) -> tuple[list[dict], dict, set]:
    """The kills, the attempts that ended before their kill, and every episode key some attempt journaled.
    Once the journal holds every episode, the remaining kills are write-phase kills."""
    rng = random.Random(args.seed)
    kills, ended, journaled = [], Counter(), set()
    while len(kills) < args.kills:
        before = len(journal_episodes(folder))
        timed = len(kills) < args.kills - args.write_kills and before < episodes
        kill = timed_kill(cfg, folder, args, rng) if timed else write_kill(cfg, folder, args)
        if kill is None:
            ended["timed" if timed else "write"] += 1
            print(f"{'timed' if timed else 'write-phase'} attempt ended before its kill ({dict(ended)})", flush=True)
            if ended["write"] > args.max_write_misses:
                raise RuntimeError(f"{ended['write']} write-phase attempts missed: try a smaller --poll")
            continue
        kills.append({**kill, "episodes_before": before, **after_kill(folder)})
        journaled |= {episode_key(r) for r in journal_episodes(folder)}
        print(f"kill {len(kills)}/{args.kills}: {kills[-1]}", flush=True)
    return kills, dict(ended), journaled


# The weights each soakable model's cells run with: pi0.5's demo policy (random weights, no download), and
# Meta-World's scripted experts, which have none.
SOAK_WEIGHTS = {"pi05": {"variant": "demo", "checkpoint": "lerobot/pi05_libero_finetuned_v044"},
                "metaworld_expert": {"variant": "full"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", default="libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn")
    parser.add_argument("--tasks", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--episodes-per-task", type=int, default=7)
    parser.add_argument("--max-steps", type=lambda text: None if text == "suite" else int(text), default=10,
                        help="policy steps per episode; `suite`: the suite's own limit")
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--write-kills", type=int, default=3, help="how many of the kills land during record writes")
    parser.add_argument("--seed", type=int, default=0, help="the RNG that times the kills")
    parser.add_argument("--window", type=float, default=None,
                        help="seconds after the running/append anchors (default: half a round of the reference run)")
    parser.add_argument("--startup-window", type=float, default=None,
                        help="seconds after launch (default: the reference run's start-up time)")
    parser.add_argument("--anchor-p", type=float, nargs=3, default=[0.3, 0.5, 0.2], metavar=("STARTUP", "RUNNING", "APPEND"),
                        help="how often a timed kill counts from each anchor")
    parser.add_argument("--poll", type=float, default=0.002, help="seconds between looks for the writer's temporary files")
    parser.add_argument("--max-write-misses", type=int, default=10)
    parser.add_argument("--out", default=None, help="JSON result (default: print only)")
    args = parser.parse_args()
    if not 0 <= args.write_kills <= args.kills:
        parser.error(f"--write-kills must be between 0 and --kills ({args.kills}), not {args.write_kills}")

    model = args.ref.split("/")[2]
    if model not in SOAK_WEIGHTS:
        parser.error(f"--ref: model {model!r} has no soak weights; known: {', '.join(SOAK_WEIGHTS)}")
    study = {
        "models": {model: SOAK_WEIGHTS[model]},
        "tasks": args.tasks,
        "episodes_per_task": args.episodes_per_task,
        "runner": {"max_steps": args.max_steps, "camera_size": 64, "flow_steps": 2},
    }
    cfg = cell_config(args.ref, study)
    episodes = len(args.tasks) * args.episodes_per_task
    # The kills are timed from the reference's start-up and round unless the windows are given (the start-up
    # window is used by the startup and running anchors only): then the reference runs beside the soak.
    timed_by_reference = args.window is None or (args.startup_window is None and any(args.anchor_p[:2]))
    with tempfile.TemporaryDirectory(prefix="vqb-soak-") as tmp, ThreadPoolExecutor(1) as beside:
        reference, killed = Path(tmp) / "reference", Path(tmp) / "killed"
        reference_run = beside.submit(complete, cfg, reference, args.num_envs)
        if timed_by_reference:
            uninterrupted_run = reference_run.result()
            startup_s = uninterrupted_run["startup_s"]
            round_s = (uninterrupted_run["total_s"] - startup_s) / math.ceil(episodes / args.num_envs)
            args.window = round(round_s / 2, 2) if args.window is None else args.window
            args.startup_window = round(startup_s, 2) if args.startup_window is None else args.startup_window
            print(f"reference: {uninterrupted_run['total_s']:.1f} s, start-up {startup_s:.1f} s, round {round_s:.2f} s; "
                  f"window {args.window} s, start-up window {args.startup_window} s", flush=True)

        began = time.monotonic()
        kills, ended, journaled = soak(cfg, killed, args, episodes)
        try:
            final_s, final_error = complete(cfg, killed, args.num_envs)["total_s"], None
        except RuntimeError as err:  # e.g. a duplicated episode refused by the journal: still counted below
            final_s, final_error = None, str(err)
        soak_s = time.monotonic() - began
        if not timed_by_reference:
            uninterrupted_run = reference_run.result()
            startup_s = uninterrupted_run["startup_s"]
            print(f"reference (run beside the soak): {uninterrupted_run['total_s']:.1f} s, start-up {startup_s:.1f} s",
                  flush=True)

        lines = journal_episodes(killed)
        outcome = {episode_key(r): (r["success"], r["steps"], r["actions_sha256"]) for r in lines}
        expected = {episode_key(r): (r["success"], r["steps"], r["actions_sha256"]) for r in journal_episodes(reference)}
        counts = Counter(episode_key(r) for r in lines)
        uninterrupted = read_cell(reference)
        resumed = read_cell(killed) if final_error is None else None
        records_equal = resumed is not None and resumed.episodes.drop(columns=TIMING, errors="ignore").equals(
            uninterrupted.episodes.drop(columns=TIMING, errors="ignore"))
        recorded = set(resumed.episodes[list(KEY)].itertuples(index=False, name=None)) if resumed is not None else set()
        result = {
            "cell": args.ref,
            "episodes": len(expected),
            "kills": len(kills),
            "kills_by_phase": dict(Counter(k["phase"] for k in kills)),
            "write_phase_misses": ended.get("write", 0),
            "timed_attempts_completed_the_cell": ended.get("timed", 0),
            "lost_episodes": len((expected.keys() | journaled) - recorded),
            "duplicated_episodes": sum(n - 1 for n in counts.values()),
            "journal_torn_after_kills": sum(k["journal_torn"] for k in kills),
            "parquet_before_complete": any(k["parquet_present"] and k["episodes_journaled"] < episodes for k in kills),
            "parquet_unreadable_or_partial": any(k["parquet_present"] and k.get("parquet_rows") != episodes for k in kills),
            "temporary_files_left": temporary_files(killed),
            "final_run_error": final_error,
            "outcomes_and_digests_equal": outcome == expected,
            "records_equal_but_timing": bool(records_equal),
            "headers_equal": resumed is not None and resumed.header == uninterrupted.header,
            "reference_s": round(uninterrupted_run["total_s"], 1),
            "reference_startup_s": round(startup_s, 1),
            "reference_beside_soak": not timed_by_reference,
            "soak_s": round(soak_s, 1),
            "final_resume_s": None if final_s is None else round(final_s, 1),
            "settings": {k: v for k, v in vars(args).items() if k != "out"},
            "kill_log": kills,
            "code_commit": subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                                          text=True).stdout.strip() or None,
            "machine": {
                "cpus": os.cpu_count(),
                "load_average": [round(x, 2) for x in os.getloadavg()],
                "platform": platform.platform(),
                "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            },
        }
    print(json.dumps({k: v for k, v in result.items() if k != "kill_log"}, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    clean = (result["lost_episodes"] == 0 and result["duplicated_episodes"] == 0 and not final_error
             and not result["temporary_files_left"]
             and not result["parquet_before_complete"] and not result["parquet_unreadable_or_partial"]
             and result["outcomes_and_digests_equal"] and result["records_equal_but_timing"] and result["headers_equal"])
    sys.exit(0 if clean else 1)


if __name__ == "__main__":
    main()
