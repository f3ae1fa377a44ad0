"""LIBERO's evaluation protocol as the authors ran it: step limits per model family and suite (tasks per
suite: `envs.BENCHMARK_SUITES`; episode seeds: `envs.episodes.episode_seed`).

Plain constants, importable without the simulator or the `envs.libero` package (whose import starts
multiprocessing and LIBERO's offline setup): every table job checks its records against them
(`records.schema`). `envs.libero.suite` builds the suites on them.
"""

# Policy steps before an unfinished episode counts as a failure (settle steps not counted). The pi
# models use lerobot's limits, OpenVLA-OFT and X-VLA their own clients'; all are visible in the authors' records.
STEP_LIMITS = {
    "pi": {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300, "libero_10": 520},
    "openvla_oft": {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520},
    # X-VLA's client horizons (its libero_client.py; failures in the authors' records run to 800).
    "xvla": {"libero_spatial": 800, "libero_object": 800, "libero_goal": 800, "libero_10": 900},
}
MODEL_FAMILY = {"pi05": "pi", "pi0": "pi", "openvla_oft": "openvla_oft", "xvla": "xvla"}
