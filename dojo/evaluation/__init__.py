"""The evaluation loop: plans in, one durable result row per episode out (policies, results store, progress, recording)."""
