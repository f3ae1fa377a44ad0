"""Batched closed-loop evaluation: N LIBERO slots, the policy batched over the slots that need a
new chunk, each episode with its own random stream.

A slot observes, receives a predicted chunk, executes its first `executed_chunk` actions, then
observes again. An episode ends on success (the environment's done flag) or at `max_steps`
policy steps; its slot then starts the next pending episode while the others continue.
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

from vlaquantbench.envs.libero import EpisodeSpec, LiberoVectorEnv
from vlaquantbench.envs.libero.vector_env import ACTION_DIM
from vlaquantbench.models.adapter import PolicyAdapter


@dataclass
class _Episode:
    spec: EpisodeSpec
    generator: torch.Generator
    started: float
    actions: deque = field(default_factory=deque)
    latencies: list[float] = field(default_factory=list)
    # Digest of every executed action: reruns and batch sizes can be compared episode by episode.
    digest: Any = field(default_factory=hashlib.sha256)


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


def run_episodes(
    adapter: PolicyAdapter,
    env: LiberoVectorEnv,
    specs: Sequence[EpisodeSpec],
    max_steps: int,
    on_finished: Callable[[list[dict]], None],
) -> None:
    """Run `specs` to completion; `on_finished(records)` gets each step's finished episodes."""
    pending = deque(specs)
    slots: list[_Episode | None] = [None] * env.num_envs
    observations: list[dict | None] = [None] * env.num_envs
    task_names = {t.task_id: t.name for t in env.suite.tasks}

    def start(free: list[int]) -> None:
        starts: list[EpisodeSpec | None] = [None] * env.num_envs
        for i in free:
            if pending:
                starts[i] = pending.popleft()
                slots[i] = _Episode(starts[i], adapter.reset(starts[i].seed), time.perf_counter())
            else:
                slots[i] = None
        if any(s is not None for s in starts):
            for i, obs in enumerate(env.reset(starts)):
                if obs is not None:
                    observations[i] = obs

    start(list(range(env.num_envs)))
    while any(slot is not None for slot in slots):
        need = [i for i, slot in enumerate(slots) if slot is not None and not slot.actions]
        if need:
            began = time.perf_counter()
            chunks = adapter.act([observations[i] for i in need], [slots[i].generator for i in need])
            latency = time.perf_counter() - began
            for i, chunk in zip(need, chunks):
                slots[i].actions.extend(chunk[: adapter.executed_chunk])
                slots[i].latencies.append(latency)
        actions = np.zeros((env.num_envs, ACTION_DIM))
        for i, slot in enumerate(slots):
            if slot is not None:
                actions[i] = slot.actions.popleft()
                slot.digest.update(actions[i].tobytes())
        new_observations, successes = env.step(actions)
        finished, free = [], []
        for i, slot in enumerate(slots):
            if slot is None:
                continue
            observations[i] = new_observations[i]
            steps = env.steps[i]
            if successes[i] or steps >= max_steps:
                if not successes[i]:
                    env.release(i)
                finished.append(
                    episode_record(
                        env.suite.name,
                        slot.spec,
                        successes[i],
                        steps,
                        task_name=task_names[slot.spec.task_id],
                        wall_time_s=time.perf_counter() - slot.started,
                        policy_latency_mean_s=float(np.mean(slot.latencies)),
                        actions_sha256=slot.digest.hexdigest(),
                    )
                )
                free.append(i)
        if finished:
            on_finished(finished)
            start(free)
