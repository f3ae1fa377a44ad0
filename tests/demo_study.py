"""The study that closed-loop tests build their cells from: demo policies (the real architectures at
reduced width, seeded random weights), task 0 of LIBERO-Spatial, short episodes on 64-pixel cameras."""

CHECKPOINTS = {  # named in each cell's config and header; a demo policy loads none of them
    "pi05": "lerobot/pi05_libero_finetuned_v044",
    "pi0": "lerobot/pi0_libero_finetuned_v044",
    "openvla_oft": "moojink/openvla-7b-oft-finetuned-libero-spatial",
    "xvla": "2toINF/X-VLA-Libero",
}


def demo_study(*models: str, episodes_per_task: int = 1, max_steps: int = 10, flow_steps: int = 2, **more) -> dict:
    """A study of `models` (default: pi0.5) with the demo variant; `more` adds study keys (calibration)."""
    return {
        "models": {model: {"variant": "demo", "checkpoint": CHECKPOINTS[model]} for model in models or ("pi05",)},
        "tasks": [0],
        "episodes_per_task": episodes_per_task,
        "runner": {"max_steps": max_steps, "camera_size": 64, "flow_steps": flow_steps},
        **more,
    }
