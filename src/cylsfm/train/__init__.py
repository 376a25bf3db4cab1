"""Training: typed configuration and presets, checkpoints, and the training loop."""
