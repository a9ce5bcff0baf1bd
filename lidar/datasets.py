"""Data sets named by a spec string, for the training and evaluation command lines.

  sim             the LiDAR simulator: an endless stream of scans (`lidar.sources.SimSource`; the
                  commands' --seed picks the stream)
  kitti:DIR       a KITTI object `training` root: DIR/velodyne/*.bin with DIR/label_2 and DIR/calib
  nuscenes:DIR    a folder of nuScenes LIDAR_TOP *.pcd.bin sweeps, each with NAME_boxes.txt beside it
  native:DIR      a folder of native .npz scans (ground truth optional, see docs/data.md)
  custom:DIR      OpenPCDet's custom layout: DIR/points/NAME.npy with DIR/labels/NAME.txt, the scans of
                  DIR/ImageSets/train.txt (training) or val.txt (evaluation) when present, else all
                  (`lidar.custom`)
  samples[:DIR]   every labelled real scan in a samples folder laid out like the project's ../shared/data
                  (default: `lidar.samples.SAMPLES_DIR`): each KITTI-layout root in it (velodyne/,
                  label_2/, calib/), each nuScenes sweep with its boxes file, each KITTI scan NAME.bin with
                  NAME_label_2.txt and NAME_calib.txt beside it; for evaluation only

`list_scan_paths(parse_data_spec(spec))` lists a folder spec's scan files; `lidar.sources` reads them
(and runs the simulator) as `LabeledScan`s.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from pathlib import Path

from lidar.custom import split_names
from lidar.samples import SAMPLES_DIR
from lidar.selection import Split

SPEC_HELP = "sim, kitti:DIR, nuscenes:DIR, native:DIR, custom:DIR or samples[:DIR]"


KITTI_DIRS = ("velodyne", "label_2", "calib")


class DataKind(enum.StrEnum):
    SIM = "sim"
    KITTI = "kitti"
    NUSCENES = "nuscenes"
    NATIVE = "native"
    CUSTOM = "custom"
    SAMPLES = "samples"


@dataclass(frozen=True)
class DataSpec:
    kind: DataKind
    path: Path | None = None  # the folder (kitti, nuscenes, native, custom, samples); None for sim

    def __str__(self) -> str:
        if self.kind is DataKind.SIM:
            return "sim"
        return f"{self.kind.value}:{self.path}"


def parse_data_spec(spec: str) -> DataSpec:
    """'sim', 'kitti:DIR', 'nuscenes:DIR', 'native:DIR', 'samples[:DIR]' -> DataSpec; ValueError otherwise.

    Only the syntax is checked here; `iter_labeled` checks that the folder holds what the kind needs.
    """
    kind_text, sep, rest = spec.strip().partition(":")
    try:
        kind = DataKind(kind_text.lower())
    except ValueError:
        raise ValueError(f"data spec {spec!r}: unknown kind {kind_text!r}; expected {SPEC_HELP}") from None
    if kind is DataKind.SIM:
        if sep:
            raise ValueError(f"data spec {spec!r}: sim takes no argument (pick the stream with --seed)")
        return DataSpec(DataKind.SIM)
    if kind is DataKind.SAMPLES and not rest.strip():
        return DataSpec(kind, path=SAMPLES_DIR)
    if not rest.strip():
        raise ValueError(
            f"data spec {spec!r}: {kind.value} needs a folder ({kind.value}:DIR); expected {SPEC_HELP}"
        )
    return DataSpec(kind, path=Path(rest.strip()).expanduser())


def list_scan_paths(spec: DataSpec, split: Split = Split.TRAIN) -> list[Path]:
    """The scan files a folder spec names, in file-name order (custom: `split`'s list order, or name order);
    FileNotFoundError naming the spec and what the folder should hold when it does not."""
    if spec.kind is DataKind.SIM or spec.path is None:
        raise ValueError(f"data spec {spec}: not a folder spec")
    root = spec.path
    if not root.is_dir():
        raise FileNotFoundError(f"data spec {spec}: {root} is not a folder")
    if spec.kind is DataKind.KITTI:
        missing = [d for d in KITTI_DIRS if not (root / d).is_dir()]
        if missing:
            raise FileNotFoundError(
                f"data spec {spec}: {root} lacks {missing}; expected a KITTI training root with "
                "velodyne/, label_2/ and calib/"
            )
        files = sorted((root / "velodyne").glob("*.bin"))
        wanted = "velodyne/*.bin"
    elif spec.kind is DataKind.NUSCENES:
        files = sorted(root.glob("*.pcd.bin"))
        wanted = "*.pcd.bin sweeps (with NAME_boxes.txt beside each)"
    elif spec.kind is DataKind.SAMPLES:
        folders = sorted(p for p in root.iterdir() if p.is_dir())
        files = [f for folder in folders for f in labelled_scans(folder)]
        wanted = "labelled KITTI, KITTI-layout or nuScenes scans in its subfolders"
    elif spec.kind is DataKind.CUSTOM:
        try:
            return [root / "points" / f"{name}.npy" for name in split_names(root, split)]
        except (FileNotFoundError, ValueError) as e:
            raise type(e)(f"data spec {spec}: {e}") from None
    else:
        files = sorted(root.glob("*.npz"))
        wanted = "*.npz native scans"
    if not files:
        raise FileNotFoundError(f"data spec {spec}: no {wanted} in {root}")
    return files


def labelled_scans(folder: Path) -> list[Path]:
    """The labelled scans of one samples subfolder: a KITTI-layout root's velodyne/*.bin, the *.pcd.bin
    sweeps with a NAME_boxes.txt, the NAME.bin scans with NAME_label_2.txt and NAME_calib.txt beside them."""
    if all((folder / d).is_dir() for d in KITTI_DIRS):
        return sorted((folder / "velodyne").glob("*.bin"))
    sweeps = [p for p in folder.glob("*.pcd.bin") if p.with_name(p.name[:-8] + "_boxes.txt").is_file()]
    scans = [
        p
        for p in folder.glob("*.bin")
        if not p.name.endswith(".pcd.bin")
        and all(p.with_name(f"{p.stem}_{part}.txt").is_file() for part in ("label_2", "calib"))
    ]
    return sorted(sweeps + scans)
