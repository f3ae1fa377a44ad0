"""OpenVLA-OFT's LIBERO client conventions (`run_libero_eval.py` of the OFT release).

Parallel decoding predicts 8 actions and the client executes all 8 open-loop; the L1-regression head
is deterministic and the client fixes the model seed at 7 (paper app. on seeds), so evaluation-seed
repeats vary only the simulator's random state. Step limits 220/280/300/520, visible in the authors' records.
"""

from vlaquantbench.models.client import ClientConventions

CHUNK = 8
MODEL_SEED = 7

CLIENT = ClientConventions(executed_chunk=CHUNK, episodes_per_task=20, control_mode="delta", mujoco="3.3.2",
                           model_seed=MODEL_SEED, source="openvla-oft run_libero_eval.py; paper Sec. 5")
STEP_LIMITS = {"libero": {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520}}
