# Checkpoint -> calibration statistics -> closed-loop rollout per cell (issue: closed-loop LIBERO rollouts).
