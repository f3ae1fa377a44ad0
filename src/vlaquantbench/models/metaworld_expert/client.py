"""The experts' client conventions: one action per observation, lerobot-eval's episode count."""

from vlaquantbench.models.client import ClientConventions

# An expert computes one action from the current state (`Policy.get_action`). Meta-World's actions are
# end-effector position deltas; MuJoCo is the main environment's pin (Meta-World 3.0.0 needs >= 3.0.0).
CLIENT = ClientConventions(executed_chunk=1, episodes_per_task=50, control_mode="delta", mujoco="3.3.2",
                           source="metaworld.policies; lerobot 0.6.1 EvalConfig.n_episodes (50)")
