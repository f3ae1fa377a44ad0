"""X-VLA's LIBERO client conventions (`evaluation/libero/libero_client.py` of the X-VLA release).

The client executes the whole predicted chunk (30 actions) before querying again; actions are
absolute end-effector targets (position, 6-D rotation converted to axis-angle, gripper thresholded
at 0.5), so the arm controller runs with `use_delta=False` after the settle steps. The authors ran
19 episodes per task under this client (190 per suite). Its environment pins MuJoCo 3.1.6, which
predates the box-box collision change (paper Sec. "Evaluation-Stack Checks"): its cells run in the
`xvla` software environment (envs/xvla.lock.txt). Step limits 800/800/800/900: its client's horizons
(failures in the authors' records run to 800).
"""

from dataclasses import dataclass

from vlaquantbench.models.client import ClientConventions

CHUNK = 30


@dataclass(frozen=True)
class XVLAConventions:
    """How X-VLA's client on a benchmark feeds the policy its observations (`ADAPTER_CONVENTIONS`)."""

    domain_id: int  # X-VLA's id of the benchmark's domain (the client's `domain_id`)
    # The client turns only the main view; an env that renders the wrist view rotated 180 degrees too has it turned back.
    wrist_turned_back: bool
    source: str = ""  # where the values come from


CLIENT = ClientConventions(executed_chunk=CHUNK, episodes_per_task=19, control_mode="absolute", mujoco="3.1.6",
                           source="X-VLA libero_client.py; paper app. on benchmarks; the authors' records")
ADAPTER_CONVENTIONS = {"libero": XVLAConventions(domain_id=3, wrist_turned_back=True, source="X-VLA libero_client.py")}
STEP_LIMITS = {"libero": {"libero_spatial": 800, "libero_object": 800, "libero_goal": 800, "libero_10": 900}}
ENVIRONMENT = "xvla"
