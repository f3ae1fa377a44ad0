"""pi0.5's LIBERO client conventions (lerobot's LIBERO evaluation, as the authors ran it)."""

from vlaquantbench.models.client import ClientConventions

# 10 of the 50 predicted actions (paper Sec. 5: executing all 50 lowers success).
CLIENT = ClientConventions(executed_chunk=10, episodes_per_task=20, control_mode="delta", mujoco="3.3.2",
                           source="lerobot LIBERO evaluation; paper Sec. 5 and the authors' records")
# Policy steps before an unfinished episode counts as a failure (settle steps not counted): lerobot's LIBERO
# limits, visible in the authors' records.
STEP_LIMITS = {"libero": {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300, "libero_10": 520}}
