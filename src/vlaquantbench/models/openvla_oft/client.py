"""OpenVLA-OFT's LIBERO client conventions (`run_libero_eval.py` of the OFT release).

Parallel decoding predicts 8 actions and the client executes all 8 open-loop; the L1-regression head
is deterministic and the client fixes the model seed at 7 (paper app. on seeds), so evaluation-seed
repeats vary only the simulator's random state. Step limits 220/280/300/520, visible in the authors' records.
"""

from dataclasses import dataclass

from vlaquantbench.models.client import ClientConventions

CHUNK = 8
MODEL_SEED = 7


@dataclass(frozen=True)
class OFTConventions:
    """How OFT's client on a benchmark maps the policy's actions to the env's (`ADAPTER_CONVENTIONS`)."""

    # The gripper's sign inverted after binarizing (the client's `invert_gripper_action`): for an env that closes the
    # gripper at +1 where the training data closes it at 0 (-1 once binarized).
    gripper_inverted: bool
    source: str = ""  # where the values come from


CLIENT = ClientConventions(executed_chunk=CHUNK, episodes_per_task=20, control_mode="delta", mujoco="3.3.2",
                           model_seed=MODEL_SEED, source="openvla-oft run_libero_eval.py; paper Sec. 5")
ADAPTER_CONVENTIONS = {"libero": OFTConventions(gripper_inverted=True, source="openvla-oft run_libero_eval.py")}
STEP_LIMITS = {"libero": {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520}}
