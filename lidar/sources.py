"""Scan sources by index, for training and evaluation: `source(i) -> LabeledScan`.

- `sim`: scan i of stream `seed` is `simulate(sim_seed(seed, i), SimConfig.varied())`, an endless,
  reproducible stream (sensor presets, mounts, noise and speed drawn per scan: docs/simulator.md). Training
  uses stream 0 by default and evaluation stream 7, so held-out scans are never trained on.
- recorded data (`kitti:DIR`, `nuscenes:DIR`, `native:DIR`, `samples[:DIR]`): the folder's scans, cycled;
  training visits them in a fresh random order every pass (seeded), evaluation in file order. Samples are
  named SUBFOLDER/NAME (KITTI and the Argoverse conversion both have a 000000). A `custom:DIR` folder gives
  the scans of one split (`Split`: training reads ImageSets/train.txt, evaluation val.txt, when present),
  their classes mapped by a `ClassMap` (lidar/custom.py).
`iter_labeled(spec)` yields a data set's scans in order.
Sources are plain picklable objects, so data-loader worker processes can build scans themselves.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar.custom import check_custom_files, read_custom_scan
from lidar.datasets import DataKind, list_scan_paths, parse_data_spec
from lidar.labels import AS_IS
from lidar.readers import read_labeled
from lidar.samples import SAMPLE_FRAMES
from lidar.selection import ClassMap, Split
from lidar.sim import SimConfig, simulate
from lidar.types import LabeledScan


def sim_seed(stream: int, index: int) -> int:
    """The simulator seed of scan `index` of stream `stream` (distinct streams never share a scan)."""
    return int(np.random.SeedSequence([stream, index]).generate_state(1)[0])


@dataclass(frozen=True)
class SimSource:
    stream: int
    cfg: SimConfig = field(default_factory=SimConfig.varied)  # every sensor preset, mount, noise, speed

    def __call__(self, index: int) -> LabeledScan:
        scan = simulate(sim_seed(self.stream, index), self.cfg)
        return dataclasses.replace(scan, name=f"sim-{self.stream}-{index:06d}")

    def __len__(self) -> int:
        return 1 << 62


@dataclass(frozen=True)
class FileSource:
    paths: tuple[Path, ...]
    shuffle_seed: int | None = None  # None: file order
    root: Path | None = None  # samples: scans named SUBFOLDER/NAME, read by SAMPLE_FRAMES
    classes: ClassMap = field(default_factory=ClassMap)  # custom (points/NAME.npy): the class names

    def __call__(self, index: int) -> LabeledScan:
        n = len(self.paths)
        epoch, k = divmod(index, n)
        if self.shuffle_seed is not None:
            k = int(np.random.default_rng([self.shuffle_seed, epoch]).permutation(n)[k])
        if self.paths[k].suffix == ".npy":
            return read_custom_scan(self.paths[k], self.classes)
        if self.root is None:
            return read_labeled(self.paths[k])
        folder = self.paths[k].relative_to(self.root).parts[0]
        scan = read_labeled(self.paths[k], frame=SAMPLE_FRAMES.get(folder, AS_IS))
        return dataclasses.replace(scan, name=f"{folder}/{scan.name}")

    def __len__(self) -> int:
        return len(self.paths)


def scan_source(
    spec: str,
    seed: int,
    shuffle: bool = True,
    split: Split = Split.TRAIN,
    classes: ClassMap | None = None,
) -> SimSource | FileSource:
    """A data spec (`sim`, `kitti:DIR`, ...) -> its source; `seed` picks the sim stream or the shuffling;
    `split` and `classes` (None: the default map) apply to `custom:DIR`, and a class map to nothing else."""
    parsed = parse_data_spec(spec)
    if classes is not None and classes != ClassMap() and parsed.kind is not DataKind.CUSTOM:
        raise ValueError(f"data {spec!r}: a class map applies to custom:DIR data only")
    if parsed.kind is DataKind.SIM:
        return SimSource(seed)
    paths = tuple(list_scan_paths(parsed, split))
    if not paths:
        raise ValueError(f"data {spec!r}: no scans found")
    if parsed.kind is DataKind.CUSTOM:  # every label file parses, before a run starts
        check_custom_files(list(paths), classes or ClassMap())
    root = parsed.path if parsed.kind is DataKind.SAMPLES else None
    return FileSource(paths, seed if shuffle else None, root, classes or ClassMap())


def iter_labeled(
    spec: str, seed: int = 0, split: Split = Split.TRAIN, classes: ClassMap | None = None
) -> Iterator[LabeledScan]:
    """The labelled scans of a data set, in order (the simulator: endless, scans of stream `seed`; custom:
    `split`'s); a folder is checked now, before the first scan is asked for."""
    source = scan_source(spec, seed, shuffle=False, split=split, classes=classes)
    indices = itertools.count() if isinstance(source, SimSource) else range(len(source))
    return (source(i) for i in indices)
