"""Batched closed-loop evaluation: N simulator slots (any benchmark's `envs.workers.WorkerVectorEnv`), the policy batched over the slots that need a
new chunk, each episode with its own random stream.

A slot observes, receives a predicted chunk, executes its first `executed_chunk` actions inside its
worker (one round trip per chunk), then observes again. An episode ends on success (the
environment's done flag), at `max_steps` policy steps, or before a non-finite action; its slot then
starts the next pending episode while the others continue.

With `overlap` (the default) the policy computes the next chunks of the slots that have replied
while the other slots still execute theirs, so the simulator need not wait for the policy. Which
episodes share a policy call then depends on timing, but an episode's actions do not: its noise
comes from its own stream, and on the CPU the adapter's linears are batch-invariant. Without
`overlap` every slot's chunk is collected before the next policy call (lockstep), which makes the
batches themselves reproducible (rollout calibration records per-call statistics).

`min_batch` (with `overlap`) holds the ready slots until at least that many are ready, or until no
slot is still stepping: fewer, larger policy calls, each ready slot waiting a little longer. On a GPU
whose chunk costs nearly as much at batch 8 as the rows it computes, fewer calls mean less GPU time
per chunk (benchmarks/HISTORY.md, closed loop on an H200).

Non-finite actions (a collapsed quantized policy outputs NaN) never reach MuJoCo: the episode ends
as a failure after the finite actions before the first non-finite one (an action the episode would
execute; a success before it ends the episode as usual), and its record says
`nonfinite_action: true`.

Each record holds the smoothness of the episode's executed actions (`jerk`, `action_rate`, defined in
`records.smoothness`) next to their digest.
"""

from __future__ import annotations

import hashlib
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.workers import WorkerVectorEnv
from vlaquantbench.models.adapter import PolicyAdapter
from vlaquantbench.records.smoothness import smoothness


@dataclass
class _Episode:
    spec: EpisodeSpec
    generator: torch.Generator
    started: float
    sent: np.ndarray | None = None  # the actions of the chunk in flight
    nonfinite: bool = False  # the chunk in flight stops before a non-finite action
    latencies: list[float] = field(default_factory=list)
    # The scene a seeded variation drew (e.g. an object and goal placement), when the env reports
    # one at reset; a scene that is an official init state is recorded by id.
    task_variation: list[float] | None = None
    # Digest of every executed action: reruns and batch sizes can be compared episode by episode.
    digest: Any = field(default_factory=hashlib.sha256)
    executed: list[np.ndarray] = field(default_factory=list)  # the executed actions, for their smoothness


def episode_record(suite: str, spec: EpisodeSpec, success: bool, steps: int, **extra) -> dict:
    return {
        "suite": suite,
        "task_id": spec.task_id,
        "episode": spec.episode,
        "seed": spec.seed,
        "init_state_id": spec.init_state_id,
        "success": bool(success),
        "steps": int(steps),
        **extra,
    }


def latency_record(latencies: Sequence[float], steps: int) -> dict:
    """An episode's latencies as the authors' latency records name them: `inference_latency_mean_s`,
    the mean duration of the policy calls that computed its chunks (full inference; with several
    slots, the batched call that computed theirs too, as `policy_batch_latency_mean_s`, kept for the
    records before these fields); `policy_latency_mean_s`, the mean per control step (the inference
    time spread over the steps, the executed actions of a chunk costing no policy call here where
    the authors' cached-action calls cost microseconds); `peak_vram_gb`, the process's peak CUDA
    allocation so far (absent on the CPU). At one slot (`--num-envs 1`, the authors' setting) they
    are the authors' quantities."""
    record = {"policy_batch_latency_mean_s": float(np.mean(latencies)) if latencies else float("nan")}
    record["inference_latency_mean_s"] = record["policy_batch_latency_mean_s"]
    record["policy_latency_mean_s"] = float(np.sum(latencies)) / steps if steps else float("nan")
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        record["peak_vram_gb"] = torch.cuda.max_memory_allocated() / 2**30
    return record


def finite_prefix(actions: np.ndarray) -> int:
    """How many leading actions (rows) are entirely finite."""
    bad = ~np.isfinite(actions).all(axis=1)
    return int(bad.argmax()) if bad.any() else len(actions)


def run_episodes(
    adapter: PolicyAdapter,
    env: WorkerVectorEnv,
    specs: Sequence[EpisodeSpec],
    max_steps: int,
    on_finished: Callable[[list[dict]], None],
    *,
    overlap: bool = True,
    min_batch: int = 1,
    on_actions: Callable[[EpisodeSpec, dict, np.ndarray], None] | None = None,
) -> None:
    """Run `specs` to completion; `on_finished(records)` gets the episodes that finish together, and
    `on_actions(spec, observation, actions)` every observation of an episode with the actions it
    executes from it (what a demonstration recorder stores), as they are sent."""
    if min_batch < 1:
        raise ValueError(f"min_batch must be at least 1, got {min_batch}")
    pending = deque(specs)
    episodes: dict[int, _Episode] = {}
    task_names = {t.task_id: t.name for t in env.suite.tasks}

    def start(slot: int) -> None:
        if pending:
            spec = pending.popleft()
            episodes[slot] = _Episode(spec, adapter.reset(spec.seed), time.perf_counter())
            env.submit_reset(slot, spec)
        else:
            episodes.pop(slot, None)

    def record(slot: int, success: bool) -> dict:
        episode = episodes[slot]
        if not success:
            env.release(slot)
        return episode_record(
            env.suite.name,
            episode.spec,
            success,
            env.steps[slot],
            task_name=task_names[episode.spec.task_id],
            wall_time_s=time.perf_counter() - episode.started,
            # One policy call computes the chunks of every slot in its batch: this is its duration.
            **latency_record(episode.latencies, env.steps[slot]),
            nonfinite_action=episode.nonfinite and not success,
            actions_sha256=episode.digest.hexdigest(),
            **smoothness(np.concatenate(episode.executed) if episode.executed else np.empty((0, 0))),
            **({} if episode.task_variation is None else {"task_variation": episode.task_variation}),
        )

    def finish(records: list[tuple[int, dict]]) -> None:
        if records:
            on_finished([r for _, r in records])
            for slot, _ in records:
                start(slot)  # the new episode resets while the policy computes the others' chunks

    for slot in range(env.num_envs):
        start(slot)
    ready: dict[int, dict] = {}  # slot -> observation, waiting for the policy
    while episodes:
        finished: list[tuple[int, dict]] = []
        for reply in env.collect(every=not overlap) if env.pending else ():
            episode = episodes[reply.slot]
            if episode.sent is not None:
                episode.digest.update(episode.sent[: reply.applied].tobytes())
                episode.executed.append(episode.sent[: reply.applied])
                episode.sent = None
            elif "task_variation" in reply.observation:  # a reset's reply
                episode.task_variation = [float(x) for x in reply.observation["task_variation"]]
            if reply.success or episode.nonfinite or env.steps[reply.slot] >= max_steps:
                finished.append((reply.slot, record(reply.slot, reply.success)))
            else:
                ready[reply.slot] = reply.observation
        finish(finished)
        if ready and (len(ready) >= min_batch or not env.pending):
            slots = list(ready)
            observations = [ready.pop(i) for i in slots]
            began = time.perf_counter()
            chunks = adapter.act(observations, [episodes[i].generator for i in slots])
            latency = time.perf_counter() - began
            for slot, observation, chunk in zip(slots, observations, chunks):
                episode = episodes[slot]
                episode.latencies.append(latency)
                # float64, as MuJoCo receives them: the digest hashes exactly what is executed.
                actions = np.asarray(chunk[: min(adapter.executed_chunk, max_steps - env.steps[slot])], np.float64)
                finite = finite_prefix(actions)
                episode.nonfinite = finite < len(actions)
                if finite:
                    episode.sent = actions[:finite]
                    env.submit_chunk(slot, episode.sent)
                    if on_actions is not None:
                        on_actions(episode.spec, observation, episode.sent)
                else:  # the chunk's first action is already non-finite
                    finish([(slot, record(slot, False))])
