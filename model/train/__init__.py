"""Training: targets, losses, the streaming training step and loop (`phim train`)."""
