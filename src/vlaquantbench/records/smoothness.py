"""Smoothness of an episode's executed actions (issue 31 item 6): jerk and action rate, in every episode record.

For the T actions a_0 .. a_{T-1} an episode executed (the rows MuJoCo received, on the env's action scale: every
dimension of its command, gripper included; control step = the time unit), with ||.|| the Euclidean norm over the
action's dimensions:

    action_rate = 1/(T-1) * sum_{t=1}^{T-1} ||a_t - a_{t-1}||^2                         (first difference)
    jerk        = 1/(T-3) * sum_{t=3}^{T-1} ||a_t - 3 a_{t-1} + 3 a_{t-2} - a_{t-3}||^2   (third difference)

i.e. the mean squared first and third finite differences per control step. An episode with fewer than 2
(4) executed actions has no action rate (jerk): the field is left out (null), not set to 0. The gripper's
open/close command (-1 / +1) is included: a chattering gripper is jerky motion on a real arm too.
"""

from __future__ import annotations

import numpy as np

SMOOTHNESS_FIELDS = ("action_rate", "jerk")
_ORDERS = {"action_rate": 1, "jerk": 3}


def smoothness(actions: np.ndarray) -> dict[str, float]:
    """The defined fields for a (T, action_dim) array of executed actions; those T is too short for are absent."""
    actions = np.asarray(actions, dtype=np.float64)
    if actions.ndim != 2:
        raise ValueError(f"executed actions must be (steps, action_dim), got shape {actions.shape}")
    return {name: float((np.diff(actions, n=order, axis=0) ** 2).sum(axis=1).mean())
            for name, order in _ORDERS.items() if len(actions) > order}
