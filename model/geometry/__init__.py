"""Geometry: boxes and their rotated IoU, NMS, sparse tensors on the polar grid, sparse-conv rule books."""
