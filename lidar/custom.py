"""OpenPCDet's custom data set layout (`custom:DIR`): the layout most LiDAR users already have. Numpy only.

    DIR/points/NAME.npy        float32 (N, 4+): x, y, z, intensity (0-1), then any further columns
    DIR/labels/NAME.txt        one box a line: x y z dx dy dz heading class
    DIR/ImageSets/train.txt    optional: the NAMEs `phim train` reads, one a line
    DIR/ImageSets/val.txt      optional: the NAMEs `phim eval` and `phim diagnose` read
Without the split's file, every points/*.npy is read, in name order.

Frame (OpenPCDet's unified one, PHiM's too): points in the LiDAR's frame, x forward, y left, z up, origin at
the sensor; (x, y, z) the box centre, dx the size along the heading, dy across it, dz the height, heading in
radians counter-clockwise about z from +x. Scans are taken to spin counter-clockwise (`Spin.CCW`); the points'
order does not matter (training and evaluation cut them into sectors by azimuth).

Classes (`lidar.selection.ClassMap`): without a map, VEHICLE, PEDESTRIAN and CYCLIST (any case:
OpenPCDet's example names Vehicle, Pedestrian, Cyclist) are themselves; a map such as
`Car=VEHICLE,Truck=VEHICLE,Misc=IGNORE` adds names, and `*=IGNORE` drops every class it does not name. Any
other class is an error naming its file and line, as is every malformed label line and points file
(`CustomDataError`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lidar.readers import sector_of_xy
from lidar.selection import ANY, IGNORE, ClassMap, Split
from lidar.types import CLASS_NAMES, GroundTruth, LabeledScan, Spin

POINTS_DIR, LABELS_DIR, SPLITS_DIR = "points", "labels", "ImageSets"
LABEL_COLUMNS = ("x", "y", "z", "dx", "dy", "dz", "heading", "class")


class CustomDataError(ValueError):
    """A custom data set's file is malformed; the message names the file (and line) and what was expected."""


def split_names(root: Path, split: Split) -> list[str]:
    """The scan NAMEs of `split`: ImageSets/SPLIT.txt when there is one, else every points/*.npy by name.
    FileNotFoundError when the folder lacks points/ or labels/ or holds no scan; CustomDataError naming the
    list's file and line for a listed name without its points file."""
    missing = [d for d in (POINTS_DIR, LABELS_DIR) if not (root / d).is_dir()]
    if missing:
        raise FileNotFoundError(
            f"{root} lacks {missing}; expected OpenPCDet's custom layout: points/NAME.npy, labels/NAME.txt, "
            "optional ImageSets/train.txt and val.txt"
        )
    listing = root / SPLITS_DIR / f"{split.value}.txt"
    if not listing.is_file():
        names = sorted(p.stem for p in (root / POINTS_DIR).glob("*.npy"))
        if not names:
            raise FileNotFoundError(f"{root / POINTS_DIR}: no *.npy points files")
        return names
    names = []
    for n, line in enumerate(_lines(listing), 1):
        name = line.strip()
        if not name:
            continue
        if not (root / POINTS_DIR / f"{name}.npy").is_file():
            raise CustomDataError(f"{listing}:{n}: {name!r} has no points file {POINTS_DIR}/{name}.npy")
        names.append(name)
    if not names:
        raise CustomDataError(f"{listing}: names no scan")
    return names


def _lines(path: Path) -> list[str]:
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as e:
        raise CustomDataError(f"{path}: not a UTF-8 text file ({e})") from None


def _check_header(path: Path, points: np.ndarray) -> None:
    """CustomDataError naming `path` unless `points` is float32 (N, 4+)."""
    if points.dtype != np.float32:
        raise CustomDataError(f"{path}: dtype {points.dtype}, expected float32 (points.astype(np.float32))")
    if points.ndim != 2 or points.shape[1] < 4:
        raise CustomDataError(f"{path}: shape {points.shape}, expected (N, 4+): x, y, z, intensity[, ...]")


def _load(path: Path, mmap: bool) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False, mmap_mode="r" if mmap else None)
    except (OSError, ValueError) as e:
        raise CustomDataError(f"{path}: not a numpy .npy array ({e})") from None


def check_custom_files(points_paths: list[Path], classes: ClassMap, points: bool = False) -> None:
    """Before a run reads them: every label file of `points_paths` (DIR/points/NAME.npy) parses, and every
    points file is float32 (N, 4+) (its header only; with `points`, all of `read_custom_points`' checks);
    CustomDataError naming the first bad file and line."""
    for path in points_paths:
        if points:
            read_custom_points(path)
        else:
            _check_header(path, _load(path, mmap=True))
        read_custom_labels(_label_path(path), classes)


def _label_path(points_path: Path) -> Path:
    label_path = points_path.parent.parent / LABELS_DIR / f"{points_path.stem}.txt"
    if not label_path.is_file():
        raise CustomDataError(f"{points_path}: no label file {label_path}")
    return label_path


def read_custom_points(path: Path) -> np.ndarray:
    """points/NAME.npy -> (N, C >= 4) float32; CustomDataError naming the file for a wrong dtype or shape,
    a non-finite value or an intensity outside [0, 1]."""
    points = _load(path, mmap=False)
    _check_header(path, points)
    bad = ~np.isfinite(points).all(axis=1)  # (N,)
    if bad.any():
        raise CustomDataError(
            f"{path}: {int(bad.sum())} of {len(points)} points have a NaN or infinite value "
            f"(the first: row {int(np.argmax(bad))})"
        )
    intensity = points[:, 3]  # (N,)
    if len(points) and (intensity.min() < 0.0 or intensity.max() > 1.0):
        raise CustomDataError(
            f"{path}: intensity (the 4th column) spans {intensity.min():g}..{intensity.max():g}, expected "
            "0..1 (scale it, e.g. / 255, or set it to 0 when the sensor has none)"
        )
    return np.ascontiguousarray(points)


def read_custom_labels(path: Path, classes: ClassMap) -> tuple[np.ndarray, np.ndarray]:
    """labels/NAME.txt -> boxes (M, 7) float32 x, y, z, l, w, h, yaw (heading wrapped to [-pi, pi)) and
    labels (M,) int64 CLASS_NAMES indices, IGNOREd classes left out; blank lines and lines starting with #
    are skipped. CustomDataError naming the file and line of a bad line."""
    table = classes.table()
    boxes, labels = [], []
    for n, line in enumerate(_lines(path), 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        where = f"{path}:{n}"
        cols = text.split()
        if len(cols) != len(LABEL_COLUMNS):
            raise CustomDataError(
                f"{where}: {len(cols)} columns, expected {len(LABEL_COLUMNS)}: {' '.join(LABEL_COLUMNS)}"
            )
        try:
            values = [float(c) for c in cols[:7]]
        except ValueError:
            raise CustomDataError(f"{where}: a non-number among x y z dx dy dz heading: {text!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise CustomDataError(f"{where}: NaN or infinity among x y z dx dy dz heading: {text!r}")
        if min(values[3:6]) <= 0.0:
            raise CustomDataError(f"{where}: box size dx dy dz {values[3:6]} must be positive")
        name = cols[7]
        if name.lower() not in table:
            if classes.ignore_others:
                continue
            raise CustomDataError(
                f"{where}: class {name!r} is not in the class map ({str(classes) or 'none given'}); map it "
                f"with --class-map {name}=VEHICLE (or PEDESTRIAN, CYCLIST, {IGNORE}), or add {ANY}={IGNORE}"
            )
        index = table[name.lower()]
        if index is not None:
            values[6] = (values[6] + math.pi) % (2 * math.pi) - math.pi
            boxes.append(values)
            labels.append(index)
    return np.asarray(boxes, np.float32).reshape(-1, 7), np.asarray(labels, np.int64)


def custom_fields(columns: int) -> tuple[str, ...]:
    """Column names of a (N, columns) points file: x, y, z, intensity, then extra4, extra5, ... (carried,
    never read as a model's elongation)."""
    return ("x", "y", "z", "intensity", *(f"extra{i}" for i in range(4, columns)))


def read_custom_scan(points_path: Path, classes: ClassMap, sectors: int = 4) -> LabeledScan:
    """DIR/points/NAME.npy with DIR/labels/NAME.txt -> LabeledScan (a missing label file: CustomDataError;
    an empty one: a scan without objects)."""
    points = read_custom_points(points_path)
    boxes, labels = read_custom_labels(_label_path(points_path), classes)
    gt = GroundTruth.from_boxes(boxes, labels, points)
    sector = sector_of_xy(points[:, 0], points[:, 1], sectors)  # (N,)
    fields = custom_fields(points.shape[1])
    return LabeledScan(points_path.stem, points, fields, gt, None, sector, None, Spin.CCW)


def write_custom_scan(root: Path, scan: LabeledScan, class_names: tuple[str, ...] = CLASS_NAMES) -> None:
    """Write a LabeledScan into the custom layout under `root` as points/NAME.npy (x, y, z, intensity) and
    labels/NAME.txt, each class written as `class_names[label]` (e.g. the test's and demo's KITTI names)."""
    (root / POINTS_DIR).mkdir(parents=True, exist_ok=True)
    (root / LABELS_DIR).mkdir(parents=True, exist_ok=True)
    cols = [scan.fields.index(f) for f in ("x", "y", "z", "intensity")]
    np.save(root / POINTS_DIR / f"{scan.name}.npy", np.ascontiguousarray(scan.points[:, cols], np.float32))
    lines = [
        " ".join(f"{v:.6f}" for v in box) + f" {class_names[int(label)]}\n"
        for box, label in zip(scan.gt.boxes, scan.gt.labels, strict=True)
    ]
    (root / LABELS_DIR / f"{scan.name}.txt").write_text("".join(lines))


def write_splits(root: Path, splits: dict[Split, list[str]]) -> None:
    """ImageSets/SPLIT.txt for each split: its NAMEs, one a line."""
    (root / SPLITS_DIR).mkdir(parents=True, exist_ok=True)
    for split, names in splits.items():
        (root / SPLITS_DIR / f"{split.value}.txt").write_text("".join(f"{n}\n" for n in names))
