"""What a run leaves: its folder, checkpoints, round records, report.html, logs, the bounded disk,
resume, the Hub, W&B, and an owner's exported policy."""
