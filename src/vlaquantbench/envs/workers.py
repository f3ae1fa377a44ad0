"""N simulator environments stepped in parallel, one worker interpreter per slot: the protocol every
benchmark's vector env offers the closed-loop runner (`runner.loop.run_episodes`).

Each slot runs its episodes independently: the runner resets a finished slot with the next episode
while the others continue. An episode's observations depend only on its EpisodeSpec and its actions,
never on the slot or the batch it ran in.

Two ways to drive the slots: `reset(specs)` / `step(actions)` exchange with every slot at once and
return when all have replied; `submit_reset(slot, spec)` / `submit_chunk(slot, actions)` send one
slot its request and return at once, and `collect()` returns the replies that have arrived, so the
caller can compute while the other slots still step (the closed-loop runner, `runner.loop`).

Workers are fresh interpreters (`python -c ...`) rather than multiprocessing children: a spawned
child re-executes the parent's `__main__` file, and a Snakemake `script:` is exactly such a file.
Each worker owns its own render context. A benchmark's vector env subclasses `WorkerVectorEnv`
(what its worker is started with, what an episode start carries, how its episodes are named in
errors); its worker serves requests with `serve`.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import traceback
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import numpy as np

import vlaquantbench
from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.memory import available_memory, oom_kill_counts, oom_kills_since, worker_gib
from vlaquantbench.errors import UserError

_SHUTDOWN_TIMEOUT_S = 10
# A request (worker start-up, env build, reset, chunk) that gets no reply for this long is a hung worker
# (e.g. a render context that never comes up when the GPU is out of memory), reported instead of waited
# on forever. Generous: env builds took minutes on a 2-core machine at load 15.
REPLY_TIMEOUT_S = 1800.0
# Workers yield the CPU to the process that drives them: with more workers than cores, the closed-loop
# runner's main process (which feeds the policy and collects the replies) would otherwise wait for a
# time slice at every step of its loop while every worker is ready to run. Moderate (a third of a
# normal process's CPU share under contention): on a machine shared with other jobs the workers
# still get their turn.
WORKER_NICENESS = 5


class WorkerError(RuntimeError):
    """A worker failed or died; the message names the slot, task and episode and carries its traceback."""


@dataclass
class _Slot:
    process: subprocess.Popen
    conn: Connection
    episode: EpisodeSpec | None = None
    live: bool = False
    steps: int = 0
    request: str | None = None  # the command sent and not yet answered


@dataclass(frozen=True)
class SlotReply:
    """A slot's answer to `submit_reset` (`applied` 0) or `submit_chunk`."""

    slot: int
    observation: dict
    applied: int  # actions applied by this request; fewer than sent only on success
    success: bool


def worker_environment() -> dict[str, str]:
    """The parent's environment, with this package importable even when it is not installed."""
    package_root = str(Path(vlaquantbench.__file__).resolve().parents[1])
    paths = [package_root, *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(dict.fromkeys(paths))}


def check_worker_settings(num_envs: int, reply_timeout_s: float) -> None:
    """UserError for settings every vector env takes, before any worker or simulator starts."""
    if num_envs < 1:
        raise UserError(f"num_envs must be at least 1, got {num_envs}")
    if not reply_timeout_s > 0:
        raise UserError(f"reply_timeout_s must be a positive number of seconds, got {reply_timeout_s}")


def _close_slots(slots: list[_Slot]) -> None:
    for slot in slots:
        try:
            slot.conn.send(("close", None))
        except OSError:
            pass
        # A worker still busy with a request sees a closed socket when it replies, and exits.
        slot.conn.close()
    for slot in slots:
        try:
            slot.process.wait(timeout=_SHUTDOWN_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            slot.process.kill()
            slot.process.wait()
    slots.clear()


class WorkerVectorEnv:
    """`reset(specs)` starts episodes in the slots given; `step(actions)` advances every live slot.

    A slot is live from its reset until its episode succeeds or the runner calls `release(slot)`
    (e.g. at the step limit). Use as a context manager, or call `close()`.

    Subclasses set `benchmark` (its `envs.BENCHMARK_SUITES` key), `simulator` (its name in errors), `action_dim`, `worker_main` (the `python -c`
    code that runs a worker with `sys.argv[1:]` = `[FD, *worker_args()]`), `worker_error`, and
    `suite` (with `task(task_id)`), and implement `_worker_args`, `_episode_start`, `_load_payload`
    and `_episode_label`; their `__init__` checks its own settings, then calls `_start_workers`.
    """

    benchmark: str
    simulator: str
    action_dim: int
    worker_main: str
    worker_error: type[WorkerError] = WorkerError
    reply_timeout_s: float = REPLY_TIMEOUT_S

    def _start_workers(self, num_envs: int) -> None:
        # Evidence for a worker that dies by SIGKILL: the memory before the workers, the kernel's OOM-kill counters.
        self._memory_at_start, self._oom_kills_at_start = available_memory(), oom_kill_counts()
        self._slots: list[_Slot] = []
        self._finalizer = weakref.finalize(self, _close_slots, self._slots)
        try:
            self._slots.extend(self._launch() for _ in range(num_envs))
            self._exchange({i: ("start", None) for i in range(num_envs)})
        except BaseException:
            self.close()
            raise

    # -- what a benchmark defines ---------------------------------------------------------------

    def _worker_args(self) -> list[str]:
        raise NotImplementedError

    def _episode_start(self, spec: EpisodeSpec) -> Any:
        """The `reset` request's payload: what the worker needs to start `spec`."""
        raise NotImplementedError

    def _load_payload(self, task_id: int) -> Any:
        """The `load` request's payload: what the worker builds a task's env from."""
        raise NotImplementedError

    def _episode_label(self, spec: EpisodeSpec) -> str:
        """How errors name an episode (suite, task, episode, scene, seed)."""
        raise NotImplementedError

    # -- public API -----------------------------------------------------------------------------

    @property
    def num_envs(self) -> int:
        return len(self._slots)

    @property
    def live(self) -> list[bool]:
        return [slot.live for slot in self._slots]

    @property
    def episodes(self) -> list[EpisodeSpec | None]:
        """The episode each slot runs or last ran."""
        return [slot.episode for slot in self._slots]

    @property
    def steps(self) -> list[int]:
        """Policy steps taken in each slot's episode (a simulator's settle steps not counted)."""
        return [slot.steps for slot in self._slots]

    @property
    def worker_pids(self) -> list[int]:
        return [slot.process.pid for slot in self._slots]

    def reset(self, slots: Sequence[EpisodeSpec | None]) -> list[dict | None]:
        """Start an episode in every slot whose entry is an EpisodeSpec; None leaves a slot as it is.

        Returns the new episodes' first observations; slots left alone get None.
        """
        self._check_open()
        if len(slots) != self.num_envs:
            raise ValueError(f"reset() takes one entry per slot ({self.num_envs}), got {len(slots)}")
        starts = {i: self._episode_start(spec) for i, spec in enumerate(slots) if spec is not None}
        for i, spec in enumerate(slots):
            if spec is not None:
                self._begin(i, spec)
        observations = self._exchange({i: ("reset", start) for i, start in starts.items()})
        for i in observations:
            self._slots[i].live = True
        return [observations.get(i) for i in range(self.num_envs)]

    def preload(self, task_ids: Sequence[int | None]) -> None:
        """Build, in every slot whose entry is a task id, that task's env now, so that the slot's next
        reset of it skips the build; what an episode observes does not change."""
        self._check_open()
        if len(task_ids) != self.num_envs:
            raise ValueError(f"preload() takes one entry per slot ({self.num_envs}), got {len(task_ids)}")
        requests = {i: ("load", self._load_payload(t)) for i, t in enumerate(task_ids) if t is not None}
        for i in requests:
            self._check_idle(i)
        self._exchange(requests)

    def step(self, actions: np.ndarray) -> tuple[list[dict | None], list[bool]]:
        """Apply `actions[i]` in every live slot i; rows of other slots are ignored.

        Returns per slot the new observation (None for slots not stepped) and success. A slot whose
        episode succeeds stops being live.
        """
        self._check_open()
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != (self.num_envs, self.action_dim):
            raise ValueError(f"actions must have shape ({self.num_envs}, {self.action_dim}), got {actions.shape}")
        live = [i for i, slot in enumerate(self._slots) if slot.live]
        for i in live:
            self._check_idle(i)
            self._check_finite(i, actions[i : i + 1])
        results = self._exchange({i: ("step", actions[i]) for i in live})
        observations: list[dict | None] = [None] * self.num_envs
        successes = [False] * self.num_envs
        for i, (observation, success) in results.items():
            observations[i], successes[i] = observation, success
            self._advance(i, 1, success)
        return observations, successes

    def submit_reset(self, slot: int, spec: EpisodeSpec) -> None:
        """Start `spec` in `slot` without waiting; its observation comes back through `collect()`."""
        self._check_open()
        start = self._episode_start(spec)
        self._begin(slot, spec)
        self._send(slot, "reset", start)

    def submit_chunk(self, slot: int, actions: np.ndarray) -> None:
        """Apply `actions` (`[k, action_dim]`) in the live `slot`, one after another inside its worker,
        without waiting; the worker stops early on success and replies once, through `collect()`."""
        self._check_open()
        actions = np.asarray(actions, dtype=np.float64)
        if actions.ndim != 2 or actions.shape[1] != self.action_dim or not len(actions):
            raise ValueError(f"a chunk must have shape (k >= 1, {self.action_dim}), got {actions.shape}")
        self._check_idle(slot)
        if not self._slots[slot].live:
            raise ValueError(f"slot {slot} has no live episode to step")
        self._check_finite(slot, actions)
        self._send(slot, "chunk", actions)

    @property
    def pending(self) -> list[int]:
        """Slots whose submitted request has not been collected yet."""
        return [i for i, slot in enumerate(self._slots) if slot.request is not None]

    def collect(self, *, every: bool = False) -> list[SlotReply]:
        """Wait until at least one pending slot has replied (`every`: all of them) and return the
        replies that have arrived, in slot order. A slot that succeeds stops being live."""
        self._check_open()
        waiting = {self._slots[i].conn: i for i in self.pending}
        if not waiting:
            raise RuntimeError("collect() with no submitted request pending")
        arrived, deadline = set(), time.monotonic() + self.reply_timeout_s
        while waiting and not (arrived and not every):
            replied = wait(list(waiting), timeout=max(0.0, deadline - time.monotonic()))
            if not replied:
                self._fail_hung(sorted(waiting.values()))
            for conn in replied:
                arrived.add(waiting.pop(conn))
        commands = {i: self._slots[i].request for i in arrived}
        replies = []
        for i, value in self._receive(sorted(arrived)).items():
            if commands[i] == "chunk":
                observation, applied, success = value
                self._advance(i, applied, success)
            else:
                observation, applied, success = value, 0, False
                self._slots[i].live = True
            replies.append(SlotReply(i, observation, applied, success))
        return replies

    def release(self, slot: int) -> None:
        """End a slot's episode without success (e.g. the step limit): it is no longer stepped."""
        self._slots[slot].live = False

    def close(self) -> None:
        self._finalizer()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- workers --------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if not self._finalizer.alive:
            raise RuntimeError(f"this {type(self).__name__} is closed")

    def _check_idle(self, i: int) -> None:
        if self._slots[i].request is not None:
            raise RuntimeError(f"slot {i} still has a {self._slots[i].request!r} request pending; collect() it first")

    def _check_finite(self, i: int, actions: np.ndarray) -> None:
        # MuJoCo integrates NaN without complaint; the runner must have stopped such an episode.
        if not np.isfinite(actions).all():
            raise ValueError(f"slot {i}: refusing non-finite actions (NaN or infinity) before they reach MuJoCo")

    def _begin(self, i: int, spec: EpisodeSpec) -> None:
        self._check_idle(i)
        if self._slots[i].process.poll() is not None:  # died earlier: give the slot a new worker
            self._replace_worker(i)
        self._slots[i].episode, self._slots[i].live, self._slots[i].steps = spec, False, 0

    def _advance(self, i: int, applied: int, success: bool) -> None:
        self._slots[i].steps += applied
        self._slots[i].live = not success

    def _launch(self) -> _Slot:
        ours, theirs = socket.socketpair()
        with theirs:
            command = [sys.executable, "-c", self.worker_main, str(theirs.fileno()), *self._worker_args()]
            process = subprocess.Popen(command, pass_fds=(theirs.fileno(),), env=worker_environment())
        return _Slot(process, Connection(ours.detach()))

    def _replace_worker(self, i: int) -> None:
        self._slots[i].conn.close()
        self._slots[i] = self._launch()
        self._exchange({i: ("start", None)})

    def _exchange(self, requests: dict[int, tuple[str, Any]]) -> dict[int, Any]:
        """Send every request first so the workers run in parallel, then collect every reply.

        "start" sends nothing and only collects the worker's start-up reply.
        """
        for i, (command, payload) in requests.items():
            if command == "start":
                self._slots[i].request = command
            else:
                self._send(i, command, payload)
        return self._receive(list(requests))

    def _send(self, i: int, command: str, payload: Any) -> None:
        try:
            self._slots[i].conn.send((command, payload))
        except OSError as error:
            self._slots[i].live = False
            raise self.worker_error(self._describe(i, command, f"could not reach the worker ({error}); "
                                                               f"{self._exit_status(i)}")) from None
        self._slots[i].request = command

    def _receive(self, slots: Sequence[int]) -> dict[int, Any]:
        """The replies of `slots` to their pending requests; `worker_error` naming every failure."""
        failures: dict[int, tuple[str, str]] = {}
        results = {}
        deadline = time.monotonic() + self.reply_timeout_s
        hung = [i for i in slots if not self._slots[i].conn.poll(max(0.0, deadline - time.monotonic()))]
        if hung:
            self._fail_hung(hung)
        for i in slots:
            command, self._slots[i].request = self._slots[i].request, None
            try:
                status, value = self._slots[i].conn.recv()
            except (EOFError, OSError):
                failures[i] = command, f"the worker died; {self._exit_status(i)}"
                continue
            if status == "ok":
                results[i] = value
            else:
                failures[i] = command, value
        if failures:
            for i in failures:
                self._slots[i].live = False
            raise self.worker_error(
                "\n\n".join(self._describe(i, command, detail) for i, (command, detail) in failures.items())
            )
        return results

    def _fail_hung(self, slots: Sequence[int]) -> None:
        """Stop the workers of `slots`, which did not answer within `reply_timeout_s`, and raise
        `worker_error` naming each; a slot's next episode gets a new worker."""
        details = []
        for i in slots:
            command, self._slots[i].request = self._slots[i].request, None
            self._slots[i].live = False
            self._slots[i].process.kill()
            self._slots[i].process.wait()
            details.append(self._describe(i, command, f"no reply within {self.reply_timeout_s:g} s: the worker "
                                                      f"hung and was stopped (pid {self._slots[i].process.pid})"))
        raise self.worker_error("\n\n".join(details))

    def _exit_status(self, i: int) -> str:
        try:
            code = self._slots[i].process.wait(timeout=_SHUTDOWN_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            return "it is still running"
        if code != -signal.SIGKILL:
            return f"exit code {code}"
        # The kernel's OOM killer sends SIGKILL; so do people and schedulers. Say "memory" only on its record.
        kills = oom_kills_since(self._oom_kills_at_start)
        if kills:
            each = worker_gib(self.benchmark, self.suite.name)
            return (f"killed by SIGKILL, likely out of memory: {self.num_envs} workers x {each} GiB vs "
                    f"{self._memory_at_start} when they started; the kernel killed for memory since ({'; '.join(kills)})")
        if not self._oom_kills_at_start:
            return f"killed by SIGKILL (exit code {code}); no OOM-kill counter is readable here to tell whether memory ran out"
        watched = ", ".join(self._oom_kills_at_start)
        return (f"killed by SIGKILL (exit code {code}); no out-of-memory kill was recorded ({watched}), so not by the "
                "kernel's OOM killer")

    def _describe(self, i: int, command: str, detail: str) -> str:
        where = f"{self.simulator} worker of slot {i} failed to {command}"
        spec = self._slots[i].episode
        if command != "start" and spec is not None:
            where += f" {self._episode_label(spec)}"
        return f"{where}:\n{detail}"


# -- the worker's side --------------------------------------------------------------------------

Handlers = dict[str, Callable[[Any], Any]]


def serve(conn: Connection, open_simulator: Callable[[], tuple[Handlers, Callable[[], None]]]) -> None:
    """Answer the parent's requests until it sends "close" or goes away.

    `open_simulator()` imports the simulator (before the start-up reply, so a broken install fails
    the start) and returns the request handlers by command and what closes the simulator. Every
    request gets one reply, `("ok", result)` or `("error", traceback)`."""
    try:
        handlers, close = open_simulator()
    except Exception:
        conn.send(("error", traceback.format_exc()))
        return
    conn.send(("ok", None))
    try:
        while True:
            try:
                command, payload = conn.recv()
            except EOFError:  # the parent is gone
                return
            if command == "close":
                return
            try:
                reply = ("ok", handlers[command](payload))
            except Exception:
                reply = ("error", traceback.format_exc())
            try:
                conn.send(reply)
            except OSError:  # the parent closed its end while we were working
                return
    finally:
        close()


def become_worker() -> None:
    """What every worker does first: leave Ctrl-C to the parent (it reaches the whole process group;
    the parent decides and closes its workers) and yield the CPU to it (`WORKER_NICENESS`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.nice(WORKER_NICENESS)
