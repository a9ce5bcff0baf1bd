"""Training: losses, the streaming training step and loop (`phim train`); the targets belong to the head."""
