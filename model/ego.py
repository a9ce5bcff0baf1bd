"""The ego vehicle: its points never reach the voxelizer, and no box centred on it is returned.

A roof-mounted sensor sees its own car: a few returns off the roof, the mirrors and the pillars within a
metre or two (KITTI's HDL-64E: 36-42 points a scan at 1-2 m, every scan at the same places), which the
detector, trained on simulated scans without an ego car, reads as an object. `PHiMConfig.ego` is the car's
footprint, a rectangle in the sensor frame (docs/model.md, "The ego vehicle"). Every path that runs the
model on a sensor's points applies it the same way: the streaming step (both engines, in one place:
`model.engine_base.EngineBase.step`), the whole-turn forward and the evaluation drop the footprint's
points first (the box refiner reads what is left), and drop the boxes whose centre lies in it last. None:
every point is read, every box returned.
"""

from __future__ import annotations

from torch import Tensor

from model.config import EgoFootprint
from model.geometry.boxes import Detections


def on_ego(ego: EgoFootprint, x: Tensor, y: Tensor) -> Tensor:
    """(N,) x, (N,) y in the sensor frame -> (N,) bool: inside the footprint."""
    return (x >= ego.x_min) & (x <= ego.x_max) & (y >= ego.y_min) & (y <= ego.y_max)


def drop_ego_points(points: list[Tensor], ego: EgoFootprint | None) -> list[Tensor]:
    """Each sector's points (N_i, C) without those inside the footprint (the tensor itself where none is)."""
    if ego is None:
        return points
    out = []
    for p in points:
        inside = on_ego(ego, p[:, 0], p[:, 1])  # (N_i,)
        out.append(p[~inside] if bool(inside.any()) else p)
    return out


def drop_ego_boxes(det: Detections, ego: EgoFootprint | None) -> Detections:
    """The detections without the boxes whose centre lies inside the footprint."""
    if ego is None or len(det) == 0:
        return det
    keep = ~on_ego(ego, det.boxes[:, 0], det.boxes[:, 1])  # (K,)
    if bool(keep.all()):
        return det
    return Detections(det.boxes[keep], det.scores[keep], det.labels[keep])
