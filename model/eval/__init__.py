"""Evaluation: Waymo-style detection metrics (AP and APH per class and difficulty level)."""
