"""SmolVLA and its local training: the policy, LoRA, lerobot's update_policy, record-level DP, evaluation
in closed loop and offline, the checks a dataset passes before training, success rates."""
