"""Ground-truth boxes of recorded scans and the targets they give (PHiM classes, label_fov), numpy only.
`lidar.readers.read_labeled` joins them with the scan's points into a `LabeledScan`.

Frame: the one `lidar.readers` reads the scans in (x forward, y left, z up); boxes (x, y, z, l, w, h,
yaw) with (x, y, z) the box centre and yaw counter-clockwise from +x.

KITTI (and KITTI-layout data such as the Argoverse conversion): label_2 boxes are in the rectified camera
frame with (x, y, z) the bottom centre; with calib R0_rect and Tr_velo_to_cam:
centre_velo = inv(R0 · Tr) · (x, y − h/2, z, 1), yaw_velo = −ry − π/2, dims (l, w, h).
KITTI labels only cover the left colour camera's image, so a KITTI `LabeledScan.label_fov` is that image's
azimuth range in the velodyne frame (`kitti_label_fov`). nuScenes: see `nuscenes_labels_for`; 360° labels.

Classes (`model.config.CLASS_NAMES`), matched case-insensitively; any other class is not a target and is
dropped (KITTI Misc, DontCare; nuScenes barrier, traffic_cone, ignore):
  KITTI: Car, Van, Truck, Tram -> VEHICLE; Pedestrian, Person_sitting -> PEDESTRIAN; Cyclist -> CYCLIST.
  nuScenes: car, truck, bus, construction_vehicle, trailer (and the full category names, emergency
  vehicles included) -> VEHICLE; pedestrian -> PEDESTRIAN; bicycle, motorcycle -> CYCLIST.
  native .npz: the names are CLASS_NAMES themselves (anything else is an error).
Points per box and Waymo difficulty come from `GroundTruth.from_boxes` (lidar/types.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar.types import CLASS_NAMES

IGNORED = ("DontCare",)
FOV_SLACK = math.radians(2.0)  # a labelled box centre may lie this far outside the camera image's azimuths
KITTI_IMAGE_WIDTH = 1242  # px: KITTI's image_2 is 1242 x 375 (1224..1242 by drive; the calib has no width)

VEHICLE, PEDESTRIAN, CYCLIST = CLASS_NAMES
KITTI_CLASSES: dict[str, str] = {  # lower-case KITTI type -> CLASS_NAMES entry
    "car": VEHICLE,
    "van": VEHICLE,
    "truck": VEHICLE,
    "tram": VEHICLE,
    "pedestrian": PEDESTRIAN,
    "person_sitting": PEDESTRIAN,
    "cyclist": CYCLIST,
}
NUSCENES_CLASSES: dict[str, str] = {  # nuScenes detection class or full category name -> CLASS_NAMES entry
    "car": VEHICLE,
    "truck": VEHICLE,
    "bus": VEHICLE,
    "construction_vehicle": VEHICLE,
    "trailer": VEHICLE,
    "pedestrian": PEDESTRIAN,
    "bicycle": CYCLIST,
    "motorcycle": CYCLIST,
    "vehicle.car": VEHICLE,
    "vehicle.truck": VEHICLE,
    "vehicle.bus.bendy": VEHICLE,
    "vehicle.bus.rigid": VEHICLE,
    "vehicle.construction": VEHICLE,
    "vehicle.trailer": VEHICLE,
    "vehicle.emergency.ambulance": VEHICLE,
    "vehicle.emergency.police": VEHICLE,
    "human.pedestrian.adult": PEDESTRIAN,
    "human.pedestrian.child": PEDESTRIAN,
    "human.pedestrian.construction_worker": PEDESTRIAN,
    "human.pedestrian.police_officer": PEDESTRIAN,
    "vehicle.bicycle": CYCLIST,
    "vehicle.motorcycle": CYCLIST,
}
NATIVE_CLASSES: dict[str, str] = {name.lower(): name for name in CLASS_NAMES}


@dataclass(frozen=True)
class LabelBoxes:
    boxes: np.ndarray  # (M, 7) float32 x, y, z, l, w, h, yaw in the velodyne frame (box centre)
    names: tuple[str, ...]  # (M,) class names as the dataset spells them


# ---- KITTI -------------------------------------------------------------------------------------------


def read_calib(path: Path) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for line in Path(path).read_text().splitlines():
        if ":" in line:
            key, values = line.split(":", 1)
            if values.strip():
                out[key.strip()] = np.array([float(v) for v in values.split()], dtype=np.float64)
    return out


def velo_from_rect(calib: dict[str, np.ndarray]) -> np.ndarray:
    """(4, 4) transform from the rectified camera frame to the velodyne frame: inv(R0 · Tr)."""
    r0 = np.eye(4)
    r0[:3, :3] = calib["R0_rect"].reshape(3, 3)
    tr = np.eye(4)
    tr[:3, :4] = calib["Tr_velo_to_cam"].reshape(3, 4)
    return np.linalg.inv(r0 @ tr)


def kitti_label_fov(
    calib: dict[str, np.ndarray], image_width: int = KITTI_IMAGE_WIDTH
) -> tuple[float, float]:
    """The azimuth range [lo, hi] (radians, velodyne frame) of the left colour camera's image.

    The rays through the image's left (u = 0) and right (u = image_width) edges at the principal row are
    (u - cx) / fx to the right per unit depth in the rectified frame (fx, cx from P2); they are turned into
    the velodyne frame with inv(R0_rect · Tr_velo_to_cam). KITTI: about -41.2° .. +40.2°.
    """
    p2 = calib["P2"].reshape(3, 4)
    fx, cx = float(p2[0, 0]), float(p2[0, 2])
    rotation = velo_from_rect(calib)[:3, :3]  # (3, 3)
    azimuths = []
    for u in (0.0, float(image_width)):
        ray = rotation @ np.array([(u - cx) / fx, 0.0, 1.0])  # (3,) direction in the velodyne frame
        azimuths.append(math.atan2(float(ray[1]), float(ray[0])))
    return min(azimuths), max(azimuths)


@dataclass(frozen=True)
class FileFrame:
    """How a recorded file departs from the conventions its format's reader assumes."""

    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the sensor's position in the file's frame (m)
    label_z_is_centre: bool = False  # KITTI label_2: the location is the box centre, not its bottom centre


AS_IS = FileFrame()  # a file that keeps its format's conventions


def read_kitti_labels(label_path: Path, calib_path: Path, z_is_centre: bool = False) -> LabelBoxes:
    m = velo_from_rect(read_calib(calib_path))
    boxes, names = [], []
    for line in Path(label_path).read_text().splitlines():
        parts = line.split()
        if len(parts) < 15 or parts[0] in IGNORED:
            continue
        h, w, length, x, y, z, ry = (float(v) for v in parts[8:15])
        centre = m @ np.array([x, y if z_is_centre else y - h / 2, z, 1.0])
        boxes.append([centre[0], centre[1], centre[2], length, w, h, -ry - math.pi / 2])
        names.append(parts[0])
    arr = np.array(boxes, dtype=np.float32).reshape(-1, 7)
    return LabelBoxes(arr, tuple(names))


def kitti_label_paths(scan_path: Path) -> tuple[Path, Path]:
    """…/velodyne/NAME.bin -> (…/label_2/NAME.txt, …/calib/NAME.txt); a scan without those, with
    NAME_label_2.txt and NAME_calib.txt beside it (a single-frame sample) -> those."""
    scan_path = Path(scan_path)
    root, name = scan_path.parent.parent, scan_path.name.split(".")[0]
    layout = root / "label_2" / f"{name}.txt", root / "calib" / f"{name}.txt"
    beside = tuple(scan_path.with_name(f"{name}_{part}.txt") for part in ("label_2", "calib"))
    if not all(p.is_file() for p in layout) and all(p.is_file() for p in beside):
        return beside[0], beside[1]
    return layout


def kitti_labels_for(scan_path: Path) -> LabelBoxes | None:
    """The labels of a KITTI velodyne scan (…/velodyne/NAME.bin -> …/label_2/NAME.txt + …/calib/NAME.txt)."""
    label, calib = kitti_label_paths(scan_path)
    if not (label.is_file() and calib.is_file()):
        return None
    return read_kitti_labels(label, calib)


# ---- nuScenes ----------------------------------------------------------------------------------------


def nuscenes_boxes_path(scan_path: Path) -> Path:
    """NAME.pcd.bin -> NAME_boxes.txt beside it."""
    scan_path = Path(scan_path)
    return scan_path.with_name(scan_path.name.removesuffix(".pcd.bin") + "_boxes.txt")


def read_nuscenes_boxes(boxes_path: Path, keep_ignored: bool = False) -> LabelBoxes:
    """A nuScenes boxes file turned into the frame `lidar.readers` reads the sweep in (x forward,
    y left: x' = y, y' = -x, yaw' = yaw - pi/2).

    The file: `class x y z l w h yaw ...` per line, box centres in the LIDAR_TOP frame (x right, y forward),
    yaw counter-clockwise from +x; `#` starts a comment; class `ignore` is skipped unless `keep_ignored`.
    """
    boxes, names = [], []
    for line in Path(boxes_path).read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#") or (parts[0] == "ignore" and not keep_ignored):
            continue
        x, y, z, length, w, h, yaw = (float(v) for v in parts[1:8])
        boxes.append([y, -x, z, length, w, h, yaw - math.pi / 2])
        names.append(parts[0])
    return LabelBoxes(np.array(boxes, dtype=np.float32).reshape(-1, 7), tuple(names))


def nuscenes_labels_for(scan_path: Path) -> LabelBoxes | None:
    """The boxes of a nuScenes LIDAR_TOP sweep (NAME.pcd.bin -> NAME_boxes.txt beside it), `ignore` skipped;
    see `read_nuscenes_boxes`."""
    boxes_path = nuscenes_boxes_path(scan_path)
    if not boxes_path.is_file():
        return None
    return read_nuscenes_boxes(boxes_path)


# ---- native .npz --------------------------------------------------------------------------------------


def read_native_gt(path: Path) -> tuple[np.ndarray, tuple[str, ...]] | None:
    """The ground truth stored in a native .npz: (boxes (M, 7) float32, names (M,)), or None without one."""
    with np.load(path, allow_pickle=False) as f:
        if "gt_boxes" not in f and "gt_names" not in f:
            return None
        if "gt_boxes" not in f or "gt_names" not in f:
            raise ValueError(f"{path}: ground truth needs both 'gt_boxes' (M, 7) and 'gt_names' (M,)")
        boxes = np.asarray(f["gt_boxes"], dtype=np.float32)
        names = tuple(str(x) for x in f["gt_names"].tolist())
    if boxes.ndim != 2 or boxes.shape[1] != 7 or boxes.shape[0] != len(names):
        raise ValueError(f"{path}: gt_boxes {boxes.shape}, {len(names)} gt_names; expected (M, 7) and (M,)")
    return boxes, names


def read_native_label_fov(path: Path) -> tuple[float, float] | None:
    """The azimuth range [lo, hi] (radians) a native file's ground truth covers; None: all around."""
    with np.load(path, allow_pickle=False) as f:
        if "label_fov" not in f:
            return None
        lo, hi = (float(v) for v in np.asarray(f["label_fov"], dtype=np.float64).reshape(2))
    return lo, hi


# ---- any format --------------------------------------------------------------------------------------


def native_labels_for(scan_path: Path) -> LabelBoxes | None:
    """The ground truth stored in a native .npz (names from CLASS_NAMES), or None without one."""
    gt = read_native_gt(scan_path)
    return None if gt is None else LabelBoxes(gt[0], gt[1])


def labels_for(scan_path: Path) -> LabelBoxes | None:
    """Ground-truth boxes of a recorded scan, if any (KITTI label_2 + calib, nuScenes boxes file, the
    ground truth inside a native .npz)."""
    scan_path = Path(scan_path)
    if scan_path.name.endswith(".pcd.bin"):
        return nuscenes_labels_for(scan_path)
    if scan_path.suffix == ".npz":
        return native_labels_for(scan_path)
    return kitti_labels_for(scan_path) if scan_path.suffix == ".bin" else None


def map_classes(labels: LabelBoxes, table: dict[str, str]) -> tuple[np.ndarray, np.ndarray]:
    """Boxes whose (lower-cased) name is in `table` -> (boxes (M', 7) float32, labels (M',) int64 index
    into CLASS_NAMES); the others are not targets and are dropped."""
    keep = [i for i, name in enumerate(labels.names) if name.lower() in table]
    classes = [CLASS_NAMES.index(table[labels.names[i].lower()]) for i in keep]
    return labels.boxes[keep].reshape(-1, 7), np.array(classes, dtype=np.int64)


def labeled_targets(
    path: Path, frame: FileFrame = AS_IS
) -> tuple[np.ndarray, np.ndarray, tuple[float, float] | None]:
    """The targets of a recorded scan, by its format: boxes (M, 7) float32, labels (M,) int64 index into
    CLASS_NAMES (classes that are not targets dropped) and the azimuth range the labels cover (None: all
    around), in the sensor's frame (`frame.origin` subtracted). FileNotFoundError when a KITTI or nuScenes
    scan has no label files beside it."""
    path = Path(path)
    shift = np.asarray(frame.origin, np.float32)
    if path.name.endswith(".pcd.bin"):
        boxes_path = nuscenes_boxes_path(path)
        if not boxes_path.is_file():
            raise FileNotFoundError(f"{path}: no nuScenes boxes file {boxes_path.name} beside it")
        return (*map_classes(_shifted(read_nuscenes_boxes(boxes_path), shift), NUSCENES_CLASSES), None)
    if path.suffix == ".npz":
        native = native_labels_for(path)
        if native is None:
            return np.zeros((0, 7), np.float32), np.zeros(0, np.int64), read_native_label_fov(path)
        unknown = sorted({n for n in native.names if n.lower() not in NATIVE_CLASSES})
        if unknown:
            raise ValueError(f"{path}: gt_names {unknown} are not among the classes {list(CLASS_NAMES)}")
        return (*map_classes(_shifted(native, shift), NATIVE_CLASSES), read_native_label_fov(path))
    label, calib = kitti_label_paths(path)
    if not (label.is_file() and calib.is_file()):
        raise FileNotFoundError(f"{path}: KITTI labels need {label} and {calib}")
    labels = _shifted(read_kitti_labels(label, calib, frame.label_z_is_centre), shift)
    fov = labelled_fov(kitti_label_fov(read_calib(calib)), labels.boxes)
    return (*map_classes(labels, KITTI_CLASSES), fov)


def _shifted(labels: LabelBoxes, shift: np.ndarray) -> LabelBoxes:
    boxes = labels.boxes.copy()
    boxes[:, :3] -= shift
    return LabelBoxes(boxes, labels.names)


def labelled_fov(camera: tuple[float, float], boxes: np.ndarray) -> tuple[float, float]:
    """The azimuth range a KITTI-layout scan's labels cover: the camera image's (`kitti_label_fov`), unless
    a labelled box centre lies more than FOV_SLACK outside it: then the calib does not describe the camera
    that was labelled (the Argoverse conversion: image -41.7..+17.8 deg by KITTI's image width, labels
    -35..+53 deg) and the labels' own azimuth span is used."""
    if len(boxes) == 0:
        return camera
    azimuth = np.arctan2(boxes[:, 1].astype(np.float64), boxes[:, 0])  # (M,)
    lo, hi = float(azimuth.min()), float(azimuth.max())
    if lo >= camera[0] - FOV_SLACK and hi <= camera[1] + FOV_SLACK:
        return camera
    return lo - FOV_SLACK, hi + FOV_SLACK
