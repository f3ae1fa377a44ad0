"""pi0.5's client conventions: lerobot's LIBERO evaluation, as the authors ran it, and lerobot's evaluation on
Meta-World, as the checkpoints trained here (`models.pi05.trained`) run there."""

from vlaquantbench.models.client import ClientConventions

# 10 of the 50 predicted actions (paper Sec. 5: executing all 50 lowers success).
CLIENT = ClientConventions(executed_chunk=10, episodes_per_task=20, control_mode="delta", mujoco="3.3.2",
                           source="lerobot LIBERO evaluation; paper Sec. 5 and the authors' records")
# Policy steps before an unfinished episode counts as a failure (settle steps not counted): lerobot's LIBERO
# limits, visible in the authors' records.
STEP_LIMITS = {"libero": {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300, "libero_10": 520}}
# On Meta-World lerobot-eval executes the policy's `n_action_steps` (the trained checkpoints' 5 of each 10-action
# chunk: config/trained_cpu.yaml, config/trained_study.yaml) and runs `EvalConfig.n_episodes` (50) per task; Meta-World's actions are
# end-effector position deltas, and MuJoCo is the main environment's pin.
BENCHMARK_CLIENTS = {"metaworld": ClientConventions(
    executed_chunk=5, episodes_per_task=50, control_mode="delta", mujoco="3.3.2",
    source="lerobot 0.6.1 eval on Meta-World: the trained checkpoint's n_action_steps, EvalConfig.n_episodes (50)")}
