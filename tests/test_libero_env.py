"""The real LIBERO simulator in worker processes: observations, batching determinism, failures."""

import copy
import dataclasses
import os
import signal

import numpy as np
import pytest

from vlaquantbench.envs.libero import EpisodeSpec, LiberoSuite, LiberoVectorEnv, LiberoWorkerError
from vlaquantbench.errors import UserError

pytestmark = pytest.mark.slow

CAMERA = 64
STEPS = 6


@pytest.fixture(scope="module")
def suite():
    return LiberoSuite("libero_spatial")


@pytest.fixture(scope="module")
def episodes(suite):
    return [suite.episode_spec(task_id=0, episode=0), suite.episode_spec(task_id=0, episode=1)]


def fixed_actions(episode: EpisodeSpec) -> np.ndarray:
    """A fixed, episode-specific action sequence that moves the arm and closes the gripper."""
    rng = np.random.default_rng(episode.seed)
    actions = rng.uniform(-0.5, 0.5, size=(STEPS, 7))
    actions[:, 6] = np.where(np.arange(STEPS) < STEPS // 2, -1.0, 1.0)
    return actions


@pytest.fixture(scope="module")
def batch2(suite, episodes):
    """Both episodes in one env of two slots, the second started two steps after the first.

    Returns per episode the observations (after reset and after each step) and the successes.
    """
    first, second = episodes
    traces = {first: [], second: []}
    successes = {first: [], second: []}
    with LiberoVectorEnv(suite, num_envs=2, camera_size=CAMERA) as env:
        traces[first].append(env.reset([first, None])[0])
        actions = np.zeros((2, 7))
        for t in range(STEPS + 2):
            if t == 2:
                traces[second].append(env.reset([None, second])[1])
                assert env.live == [True, True]
            for slot, episode in enumerate(env.episodes):
                if env.live[slot]:
                    actions[slot] = fixed_actions(episode)[env.steps[slot]]
                else:
                    actions[slot] = np.nan  # ignored: the slot is not stepped
            observations, success = env.step(actions)
            for slot, episode in enumerate((first, second)):
                if observations[slot] is not None:
                    traces[episode].append(observations[slot])
                    successes[episode].append(success[slot])
            for slot in range(2):
                if env.live[slot] and env.steps[slot] == STEPS:
                    env.release(slot)
        assert env.steps == [STEPS, STEPS]
        assert env.live == [False, False]
        versions = env.versions
    return traces, successes, versions


def test_observations_follow_contract_6(suite, episodes, batch2):
    traces, successes, versions = batch2
    for episode in episodes:
        assert len(traces[episode]) == STEPS + 1
        assert len(successes[episode]) == STEPS
        for obs in traces[episode]:
            assert set(obs) == {"agentview", "wrist", "state", "instruction"}
            for view in ("agentview", "wrist"):
                assert obs[view].shape == (CAMERA, CAMERA, 3)
                assert obs[view].dtype == np.uint8
                assert obs[view].flags.c_contiguous
                assert obs[view].std() > 1.0  # a rendered scene, not a blank buffer
            assert obs["state"].shape == (8,)
            assert obs["state"].dtype == np.float32
            assert obs["instruction"] == suite.tasks[episode.task_id].instruction
        settled = traces[episode][0]["state"]
        assert settled[2] > 0.5  # the end effector is above the table
        assert settled[6] > 0.03 and settled[7] < -0.03  # after settling with the gripper held open
        moved = traces[episode][-1]["state"]
        assert np.abs(moved[:3] - settled[:3]).max() > 1e-3  # the actions reached the arm
    # The two init states differ, so do the first observations.
    assert not np.array_equal(traces[episodes[0]][0]["agentview"], traces[episodes[1]][0]["agentview"])
    assert versions["mujoco"] == "3.3.2" and versions["mujoco_pin_overridden"] is False


def test_batch_of_one_with_a_preloaded_env_reproduces_batch_of_two(suite, episodes, batch2):
    traces, successes, _ = batch2
    with LiberoVectorEnv(suite, num_envs=1, camera_size=CAMERA) as env:
        env.preload([episodes[0].task_id])  # built before the reset, as the runner does: nothing changes
        for episode in episodes:  # one after the other in the same slot and worker
            trace = [env.reset([episode])[0]]
            for action in fixed_actions(episode):
                observations, success = env.step(action[None])
                trace.append(observations[0])
                assert success[0] == successes[episode][len(trace) - 2]
            for single, batched in zip(trace, traces[episode], strict=True):
                np.testing.assert_array_equal(single["state"], batched["state"])
                np.testing.assert_array_equal(single["agentview"], batched["agentview"])
                np.testing.assert_array_equal(single["wrist"], batched["wrist"])

        # A worker that dies is reported with its slot, task and episode, and the slot recovers.
        os.kill(env.worker_pids[0], signal.SIGKILL)
        with pytest.raises(LiberoWorkerError, match=r"slot 0 failed to step libero_spatial task 0 .* episode 1"):
            env.step(np.zeros((1, 7)))
        assert env.live == [False]
        again = env.reset([episodes[0]])[0]
        np.testing.assert_array_equal(again["agentview"], traces[episodes[0]][0]["agentview"])


def test_bad_requests_fail_before_any_work_and_worker_errors_name_the_episode(suite, tmp_path):
    # A suite whose task 0 lost its BDDL file, as a broken install would.
    broken = copy.copy(suite)
    broken.tasks = (dataclasses.replace(suite.tasks[0], bddl_file=tmp_path / "missing.bddl"), *suite.tasks[1:])
    with LiberoVectorEnv(broken, num_envs=1, camera_size=CAMERA, settle_steps=0) as env:
        pattern = r"slot 0 failed to reset libero_spatial task 0 \(.*\) episode 2 \(init state 2, seed 2\)"
        with pytest.raises(LiberoWorkerError, match=pattern) as failure:
            env.reset([suite.episode_spec(task_id=0, episode=2)])
        assert "missing.bddl does not exist" in str(failure.value)  # the worker's traceback
        with pytest.raises(UserError, match="init_state_id 50 is out of range for libero_spatial task 3"):
            env.reset([EpisodeSpec(task_id=3, episode=50, init_state_id=50, seed=3077)])
        with pytest.raises(UserError, match="task_id 10 is out of range"):
            env.reset([EpisodeSpec(task_id=10, episode=0, init_state_id=0, seed=0)])
        with pytest.raises(ValueError, match="one entry per slot"):
            env.reset([None, None])
        with pytest.raises(ValueError, match=r"shape \(1, 7\)"):
            env.step(np.zeros(7))
        assert env.live == [False]
        observations, success = env.step(np.zeros((1, 7)))  # nothing live: nothing stepped
        assert observations == [None] and success == [False]
    with pytest.raises(RuntimeError, match="closed"):
        env.step(np.zeros((1, 7)))


def test_a_chunk_renders_each_camera_once_and_observes_as_stepping_each_action(suite, episodes):
    """The worker's chunk renders only the images its final observation carries, one per camera; every
    chunk's final observation still equals stepping the same actions one by one with rendering on."""
    from vlaquantbench.envs.libero.offline import load_libero
    from vlaquantbench.envs.libero.worker import EpisodeStart, SlotSimulator

    load_libero()
    episode, chunk = episodes[0], 10
    task = suite.task(episode.task_id)
    start = EpisodeStart(episode, str(task.bddl_file), task.instruction,
                         suite.init_state(episode.task_id, episode.init_state_id))
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (2 * chunk, 7))
    actions[:, 6] = -1.0
    simulator = SlotSimulator(CAMERA, settle_steps=10)
    try:
        simulator.start(start)
        stepped = [simulator.step(action)[0] for action in actions]
        simulator.start(start)  # same task: the environment is kept, the episode restarts
        mj_sim = simulator._env.env.sim
        renders, render = [], mj_sim.render
        mj_sim.render = lambda *args, **kwargs: renders.append(kwargs["camera_name"]) or render(*args, **kwargs)
        chunked = [simulator.chunk(actions[i : i + chunk]) for i in range(0, len(actions), chunk)]
    finally:
        simulator.close()
    for k, (observation, applied, success) in enumerate(chunked):
        assert (applied, success) == (chunk, False)
        reference = stepped[(k + 1) * chunk - 1]
        for key in ("agentview", "wrist", "state"):
            np.testing.assert_array_equal(observation[key], reference[key])
    assert len(renders) == 2 * len(chunked)  # two cameras, once per chunk


def test_a_start_renders_only_the_settled_images_and_observes_as_stepping_the_no_ops(suite, episodes, monkeypatch):
    """The settle no-ops after an init state is loaded run as a chunk: each camera renders once for
    them (its settled image), and the start's observation equals stepping the no-ops one by one with
    rendering on, as LIBERO's evaluation clients do."""
    from robosuite.utils.binding_utils import MjSim

    from vlaquantbench.envs.libero.offline import load_libero
    from vlaquantbench.envs.libero.worker import DUMMY_ACTION, EpisodeStart, SlotSimulator, format_observation

    load_libero()
    episode = episodes[1]
    task = suite.task(episode.task_id)
    start = EpisodeStart(episode, str(task.bddl_file), task.instruction,
                         suite.init_state(episode.task_id, episode.init_state_id))
    renders, render = [], MjSim.render
    monkeypatch.setattr(MjSim, "render", lambda *args, **kwargs: renders.append(kwargs["camera_name"]) or render(*args, **kwargs))
    counts = {}
    for settle_steps in (0, 10):
        simulator = SlotSimulator(CAMERA, settle_steps=settle_steps)
        try:
            simulator.load(start.bddl_file)
            renders.clear()
            observation = simulator.start(start)
            counts[settle_steps] = len(renders)
            if settle_steps:
                libero_env = simulator._env  # the same start, every no-op stepped with its renders
                libero_env.seed(episode.seed)
                libero_env.reset()
                libero_env.set_init_state(start.init_state)
                for _ in range(settle_steps):
                    raw, _, _, _ = libero_env.step(DUMMY_ACTION)
                reference = format_observation(raw, task.instruction)
        finally:
            simulator.close()
    for key in ("agentview", "wrist", "state"):
        np.testing.assert_array_equal(observation[key], reference[key])
    assert counts[10] == counts[0] + 2  # the reset and the init state's renders, then one per camera


@pytest.mark.parametrize(
    ("substep", "rate", "offset"),
    [(0.002, 20, 0), (0.002, 20, 1), (0.002, 20, 24), (0.002, 20, 25),  # LIBERO's, after 0 to 25 forced updates
     (0.005, 20, 0),  # float drift stretches one period to 11 substeps
     (0.01, 20, 0),  # the timer lands exactly on the period
     (0.002, 15, 0)])  # periods of 33 and 34 substeps
def test_sampled_again_predicts_robosuites_next_sample(substep, rate, offset):
    """`sampled_again` against a real robosuite Observable stepped substep by substep: from every
    sample, it tells whether another comes within the substeps left, whatever the timer's start (a
    reset's forced updates advance it), its float drift and periods of varying substeps."""
    from robosuite.utils.observables import Observable, sensor

    from vlaquantbench.envs.libero.worker import sampled_again

    sampled_at, timers, observables = [], [], []
    clock = {"substep": 0}

    @sensor(modality="image")
    def camera(obs_cache):
        if observables:  # not the constructor's validity check
            sampled_at.append(clock["substep"])
            timers.append(observables[0]._time_since_last_sample)
        return np.zeros((2, 2, 3))

    observables.append(Observable("camera", camera, sampling_rate=rate))
    observable = observables[0]
    for clock["substep"] in range(offset):  # forced updates, as at a reset
        observable.update(substep, {}, force=True)
    sampled_at.clear(), timers.clear()
    total = 6000
    for clock["substep"] in range(total):
        observable.update(substep, {})
    assert len(sampled_at) > 100
    for position, (at, timer) in enumerate(zip(sampled_at, timers)):
        following = sampled_at[position + 1] if position + 1 < len(sampled_at) else total
        for end in range(at + 1, min(following + 3, total + 1)):  # the chunk ends after substep end - 1
            assert sampled_again(timer, 1 / rate, substep, end - at - 1) == (following < end), (at, end)


def test_a_hung_worker_is_stopped_and_named_instead_of_waited_on_forever(suite, episodes):
    # SIGSTOP freezes a real worker as a render context that never comes up would: no reply, no exit.
    with LiberoVectorEnv(suite, num_envs=1, camera_size=CAMERA, reply_timeout_s=3) as env:
        first = env.worker_pids[0]
        os.kill(first, signal.SIGSTOP)
        with pytest.raises(LiberoWorkerError, match=r"slot 0 failed to load:\nno reply within 3 s: the worker hung"):
            env.preload([0])
        assert not os.path.exists(f"/proc/{first}")  # killed and reaped, not left stopped
        # The slot's next episode gets a new worker; a hang there is named with the episode (collect path).
        env.submit_reset(0, episodes[1])
        second = env.worker_pids[0]
        assert second != first
        os.kill(second, signal.SIGSTOP)
        with pytest.raises(LiberoWorkerError, match=r"slot 0 failed to reset libero_spatial task 0 .* episode 1 .*\n"
                                                    r"no reply within 3 s"):
            env.collect()
        assert env.live == [False] and env.pending == []
    with pytest.raises(UserError, match="reply_timeout_s must be a positive number of seconds, got 0"):
        LiberoVectorEnv(suite, num_envs=1, reply_timeout_s=0)
