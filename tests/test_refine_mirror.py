"""The refiner reads the boxes of some classes twice, as they are and as their mirror images
(`RefineConfig.mirror`, `model.layers.refine.mirrored_mean`)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from test_refine import random_scene

from model.config import PHiMConfig, RefineConfig, tiny
from model.detector import PHiM
from model.geometry.boxes import Detections
from model.layers.refine import refine_many

MIRROR = torch.tensor([1.0, -1.0, 1.0, 1.0, 1.0, 1.0, -1.0])  # a box's mirror image: y -> -y, yaw -> -yaw


def refined(classes: tuple[bool, ...], points: torch.Tensor, boxes: torch.Tensor, **kw) -> Detections:
    """The scene's boxes (classes in turn, scores falling) refined by untrained weights (seed 0), the boxes of
    `classes` read twice (`RefineConfig.mirror`)."""
    torch.manual_seed(0)
    refiner = PHiM(dataclasses.replace(tiny(), refine=RefineConfig(points=16, mirror=classes))).refiner
    det = Detections(boxes, torch.linspace(0.9, 0.3, len(boxes)), torch.arange(len(boxes)) % 3)
    return refine_many(refiner, [det], [points], **kw)[0]


def test_a_mirrored_scene_refines_to_the_mirrored_boxes_where_both_readings_are_averaged():
    """Averaged with its mirror image, each reading is its mirror image's mirrored: a scene and its mirror
    (y -> -y) refine to mirrored boxes with the same scores (a box turned by pi is the same box). Read once,
    untrained weights tell the two apart."""
    points, boxes = random_scene(1)
    mirrored_points = points * torch.tensor([1.0, -1.0, 1.0, 1.0])
    for mirror in ((True,) * 3, (False,) * 3):
        a, b = refined(mirror, points, boxes), refined(mirror, mirrored_points, boxes * MIRROR)
        turned = torch.remainder(a.boxes[:, 6] + b.boxes[:, 6] + math.pi, 2 * math.pi) - math.pi  # 0 or pi
        same = torch.allclose(a.boxes[:, :6] * MIRROR[:6], b.boxes[:, :6], atol=1e-4)
        same = same and torch.allclose(a.scores, b.scores) and bool((turned.abs() < 1e-4).all())
        assert same == all(mirror) and len(a) == len(b) > 10


def test_only_the_classes_it_names_are_read_twice_and_the_fit_reads_each_box_once():
    points, boxes = random_scene(2)
    plain = refined((False,) * 3, points, boxes)
    peds = refined((False, True, False), points, boxes)
    fit = refined((False, True, False), points, boxes, mirror=False)
    assert torch.equal(fit.boxes, plain.boxes) and torch.equal(fit.scores, plain.scores)
    for label, moved in ((0, False), (1, True), (2, False)):
        a, b = (d.boxes[d.labels == label] for d in (plain, peds))
        assert len(a) > 3 and (not torch.equal(a, b)) == moved


def test_a_refiner_saved_before_mirror_reads_each_box_once_and_the_list_needs_one_per_class():
    d = dataclasses.replace(tiny(), refine=RefineConfig()).to_dict()
    assert PHiMConfig.from_dict(d).refine.mirror == (False, True, True)
    del d["refine"]["mirror"]
    assert PHiMConfig.from_dict(d).refine.mirror == (False,) * 3
    with pytest.raises(ValueError, match="one value per class"):
        dataclasses.replace(tiny(), refine=RefineConfig(mirror=(True,)))
