"""Model configuration: one frozen dataclass per part, composed into `PHiMConfig`.

Two named configurations exist: `paper()` (the paper's Waymo settings) and `tiny()` (same architecture,
small enough to run at sensor rate on a 2-core CPU). Every choice the paper leaves open is a field here and
is explained in docs/model.md.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, field, replace

from lidar.types import CLASS_NAMES, DEFAULT_SECTORS

# point columns in the order the model reads them; a config uses the first `vfe.point_features`
POINT_FIELDS: tuple[str, ...] = ("x", "y", "z", "intensity", "elongation")


class ScanImpl(enum.StrEnum):
    """Which selective-scan implementation the Mamba layers use."""

    AUTO = "auto"  # TRITON on a CUDA device where Triton is installed, NUMBA on the CPU, else CHUNKED
    REFERENCE = "reference"  # sequential loop per sequence; slow, the ground truth
    CHUNKED = "chunked"  # packed ragged chunks, closed-form carry between chunks; CPU and CUDA
    TRITON = "triton"  # the chunked algorithm in three Triton kernels; CUDA only
    NUMBA = "numba"  # one pass over the tokens in numba kernels, forward and backward; CPU only


class Engine(enum.StrEnum):
    """How a streaming step runs (the weights are the same)."""

    EAGER = "eager"  # model.stream.StreamingDetector: data-dependent shapes, the reference
    # model.graph.engine.GraphStreamingDetector: the fixed-shape step through torch.compile(fullgraph=True)
    # (its plain twin, the same step op by op, is GraphStreamingDetector(compile=False): tests and tools)
    GRAPH = "graph"


class Precision(enum.StrEnum):
    """The dtype a streaming step's matmuls and convs run in (weights, states and outputs stay float32)."""

    FP32 = "fp32"  # everything in float32, the reference
    # torch.autocast to bfloat16 (model.precision): matmul/conv inputs rounded to bf16, float32 accumulation;
    # the selective scan's recurrence, norms and box decoding stay float32. Meant for CUDA
    BF16 = "bf16"


class MambaHistory(enum.StrEnum):
    """How far back a stream's global-Mamba state reaches (docs/model.md, "Streaming history")."""

    TURN = "turn"  # reset every sectors_per_turn sectors: each turn is encoded as training encodes a scan
    STREAM = "stream"  # carried from the stream's start (or a client's reset): far longer than training's


class HeadingCode(enum.StrEnum):
    """How the head encodes a box's yaw."""

    SIN_COS = "sin_cos"  # (sin yaw, cos yaw), regressed (CenterPoint)
    # (sin 2 yaw, cos 2 yaw) regressed: the box axis, unambiguous even where front and back look alike; plus a
    # direction logit (> 0: yaw within 90 degrees of the axis angle in (-90, 90]), as SECOND's direction
    # classifier
    AXIS_DIRECTION = "axis_direction"


@dataclass(frozen=True)
class PolarGridConfig:
    """Cylindrical voxel grid (r, theta, z). theta covers [-pi, pi) in `theta_bins` bins."""

    r_bins: int
    theta_bins: int
    z_bins: int
    r_min: float  # metres; points closer are dropped (ego returns)
    r_max: float  # metres; points farther are dropped
    z_min: float  # metres, sensor frame
    z_max: float

    @property
    def r_size(self) -> float:
        return (self.r_max - self.r_min) / self.r_bins

    @property
    def theta_size(self) -> float:
        return 2 * math.pi / self.theta_bins

    @property
    def z_size(self) -> float:
        return (self.z_max - self.z_min) / self.z_bins


@dataclass(frozen=True)
class VFEConfig:
    """Dynamic voxel feature encoder: per-point MLP with max scatter pooling per voxel (no cap on points)."""

    point_features: int = 4  # x, y, z, intensity[, elongation]
    hidden: tuple[int, ...] = (32,)


@dataclass(frozen=True)
class MambaConfig:
    d_state: int = 16
    d_conv: int = 4
    expand: int = 2
    dt_rank: int = 0  # 0 means ceil(d_model / 16), as in mamba_simple.py
    dt_min: float = 0.001
    dt_max: float = 0.1
    dt_init_floor: float = 1e-4
    scan: ScanImpl = ScanImpl.AUTO
    chunk_size: int = 32
    # False: Mamba-1, one decay per (channel, state), A = -(1..d_state) (S4D-real). True: the d_state states
    # of a channel share one decay (as Mamba-2 shares one per head), A_d = -U(1, 16): less work in the scan
    shared_decay: bool = False


@dataclass(frozen=True)
class BackboneConfig:
    """PHiM 3D backbone: one PHiM block per entry of `down_strides` / `down_kernels`."""

    d_model: int = 128
    down_strides: tuple[int, ...] = (1, 1, 1, 2, 1, 4)
    down_kernels: tuple[int, ...] = (3, 3, 3, 3, 3, 5)
    frustum_theta_bins: int = 9  # azimuth bins per frustum of the local Mamba
    # z extent of the decomposed (theta, z) conv and its inverse (the theta extent is the block's kernel):
    # 1 = an azimuth-only kernel, the paper's "(1, 3) on (z, theta)"; the kernel size k gives a square k x k
    tz_kernel_z: int = 1
    mamba: MambaConfig = field(default_factory=MambaConfig)

    def __post_init__(self) -> None:
        if len(self.down_strides) != len(self.down_kernels):
            raise ValueError("down_strides and down_kernels must have the same length (one per PHiM block)")


@dataclass(frozen=True)
class BEVConfig:
    """Cartesian BEV grid and the PillarNeXt-style residual BEV backbone."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    cell: float  # metres per BEV cell (square)
    layer_nums: tuple[int, ...] = (1, 2, 2)
    layer_strides: tuple[int, ...] = (1, 2, 2)
    num_filters: tuple[int, ...] = (128, 128, 256)
    upsample_strides: tuple[int, ...] = (1, 2, 4)
    num_upsample_filters: tuple[int, ...] = (128, 128, 128)

    @property
    def nx(self) -> int:
        return round((self.x_max - self.x_min) / self.cell)

    @property
    def ny(self) -> int:
        return round((self.y_max - self.y_min) / self.cell)


@dataclass(frozen=True)
class HeadConfig:
    """CenterPoint head and decoding."""

    class_names: tuple[str, ...] = CLASS_NAMES
    shared_channels: int = 64
    head_channels: int = 64
    head_convs: int = 2  # conv layers per regression branch, the last one is the output
    nms_iou: tuple[float, ...] = (0.75, 0.6, 0.55)  # per class, BEV rotated IoU
    score_threshold: float = 0.1
    pre_nms_top_k: int = 4096
    post_nms_top_k: int = 500
    iou_rectifier: tuple[float, ...] = (0.68, 0.71, 0.65)  # score = hm^(1-a) * iou^a, per class
    heading: HeadingCode = HeadingCode.SIN_COS

    def __post_init__(self) -> None:
        n = len(self.class_names)
        if len(self.nms_iou) != n or len(self.iou_rectifier) != n:
            raise ValueError("nms_iou and iou_rectifier need one value per class")


@dataclass(frozen=True)
class RefineConfig:
    """The box refiner (model.layers.refine): a second stage that corrects each box from its raw points."""

    points: int = 64  # points read per box (128 gained 0.010 vehicle AP on sim for twice the PointNet time)
    # metres added to l, w, h for the points read, per class (the head's order): a pedestrian's neighbours
    # stand within a metre of it (docs/simulator.md), so it reads 0.2 m around itself
    grow: tuple[tuple[float, float, float], ...] = ((1.0, 1.0, 0.5), (0.4, 0.4, 0.5), (1.0, 1.0, 0.5))
    hidden: int = 128  # channels of the pooled point feature
    iou_weight: float = 0.5  # refined score = score^(1 - a) * predicted IoU^a
    # a second per-point layer that reads each point with the first layer's pooled feature (PointNet's
    # segmentation form): the points' shape relative to the whole object, not only each alone
    context: bool = True
    # a ninth output, the logit that the box points the wrong way: above 0 the refined box turns by pi
    flip: bool = True
    # refiners applied in turn, each fitted on the boxes the ones before it refined (a cascade): a later
    # stage sees boxes closer to their objects, so it learns finer corrections and a sharper IoU
    stages: int = 2
    # per class (the head's order): every heatmap cell above the head's score threshold is a box to refine,
    # not only the 3x3 local maxima; a pedestrian beside another in the next 0.8 m cell has no peak of its
    # own, and the refiner moves each cell's box onto the person it belongs to. Not vehicles: a car covers
    # a dozen cells, whose boxes would crowd the others out of the head's post_nms_top_k
    every_cell: tuple[bool, ...] = (False, True, True)
    # per class, BEV rotated IoU: NMS over the last stage's boxes (the boxes of one object's cells meet)
    nms_iou: tuple[float, ...] = (0.75, 0.1, 0.55)
    # per class: at work each box is also read as its mirror image (y -> -y in its frame: the object seen
    # from its other side) and the two readings averaged; on the simulator pedestrians and cyclists gain
    # from it and vehicles do not (docs/model-card.md), so their boxes are not read twice
    mirror: tuple[bool, ...] = (False, True, True)

    def __post_init__(self) -> None:
        if self.stages < 1:
            raise ValueError(f"stages: {self.stages}; expected at least 1")
        if not all(len(g) == 3 and all(0 <= v < 1e3 for v in g) for g in self.grow):
            raise ValueError(f"grow: {self.grow}; expected (l, w, h) metres in [0, 1000) per class")


@dataclass(frozen=True)
class EgoFootprint:
    """The ego vehicle around the sensor: a rectangle in the sensor frame (metres; x forward, y left). Its
    points are dropped before voxelization and no box centred in it is returned (`model.ego`). The default
    fits a mid-size car with the sensor on its roof, about over its middle (docs/model.md, "The ego
    vehicle": KITTI's Passat, its own returns and the ground it hides)."""

    x_min: float = -2.5
    x_max: float = 2.5
    y_min: float = -1.6
    y_max: float = 1.6

    def __post_init__(self) -> None:
        if not (self.x_min < self.x_max and self.y_min < self.y_max):
            raise ValueError(f"ego footprint {self}: expected x_min < x_max and y_min < y_max")


@dataclass(frozen=True)
class PHiMConfig:
    name: str
    grid: PolarGridConfig
    vfe: VFEConfig
    backbone: BackboneConfig
    bev: BEVConfig
    head: HeadConfig
    sectors_per_turn: int = DEFAULT_SECTORS
    buffer_sectors: int = 3  # sectors kept per stream besides the new one (n - 1)
    history: MambaHistory = MambaHistory.TURN  # training runs one turn from a zero state: so does serving
    # the fixed-shape step's voxel rows per buffered sector (serving only, no weights: a sector with more
    # voxels fails alone); about 1.5x the most seen on the real KITTI sectors (tiny 4,254; paper 14,977)
    sector_voxels: int = 8192
    refine: RefineConfig | None = None  # the box refiner, trained after the detector (`phim train-refiner`)
    # the ego vehicle (no weights: where the model runs on a sensor's scans); None: every point is read
    ego: EgoFootprint | None = field(default_factory=EgoFootprint)

    def __post_init__(self) -> None:
        per_sector, rem = divmod(self.grid.theta_bins, self.sectors_per_turn)
        if rem:
            raise ValueError("theta_bins must be a multiple of sectors_per_turn")
        if per_sector % self.backbone.frustum_theta_bins:
            raise ValueError("theta bins per sector must be a multiple of frustum_theta_bins")
        if self.buffer_sectors < 0:
            raise ValueError("buffer_sectors must be >= 0")
        n, r = len(self.head.class_names), self.refine
        if r is not None and not len(r.grow) == len(r.every_cell) == len(r.nms_iou) == len(r.mirror) == n:
            raise ValueError("refine.grow, every_cell, nms_iou and mirror need one value per class")

    @property
    def every_cell(self) -> tuple[bool, ...]:
        """Per class, whether every heatmap cell is a candidate box (the refiner's `every_cell`; without a
        refiner only the local maxima are)."""
        return self.refine.every_cell if self.refine is not None else ()

    def resets_history(self, sectors_seen: int) -> bool:
        """Whether a stream that has seen `sectors_seen` sectors starts its next one from a zero global-Mamba
        state (a turn boundary, under MambaHistory.TURN)."""
        turn_done = sectors_seen > 0 and sectors_seen % self.sectors_per_turn == 0
        return self.history is MambaHistory.TURN and turn_done

    def reading(self, point_features: int) -> PHiMConfig:
        """This config reading the first `point_features` point columns (3: x, y, z, no intensity)."""
        return replace(self, vfe=replace(self.vfe, point_features=point_features))

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> PHiMConfig:
        b = dict(d["backbone"])
        b["mamba"] = MambaConfig(**{**b["mamba"], "scan": ScanImpl(b["mamba"]["scan"])})
        return PHiMConfig(
            name=d["name"],
            grid=PolarGridConfig(**d["grid"]),
            vfe=VFEConfig(**_tuples(d["vfe"])),
            backbone=BackboneConfig(**_tuples(b)),
            bev=BEVConfig(**_tuples(d["bev"])),
            head=HeadConfig(
                **{**_tuples(d["head"]), "heading": HeadingCode(d["head"].get("heading", "sin_cos"))}
            ),
            sectors_per_turn=d["sectors_per_turn"],
            buffer_sectors=d["buffer_sectors"],
            history=MambaHistory(d.get("history", MambaHistory.TURN)),
            sector_voxels=d.get("sector_voxels") or _default_sector_voxels(d["name"]),
            refine=_refine_config(d.get("refine"), len(d["head"].get("class_names", CLASS_NAMES))),
            ego=EgoFootprint(**d["ego"]) if d.get("ego") else None if "ego" in d else EgoFootprint(),
        )


def _default_sector_voxels(name: str) -> int:
    """For a config dict written before `sector_voxels` existed: the named config's, else the default."""
    return CONFIGS[name]().sector_voxels if name in CONFIGS else PHiMConfig.sector_voxels


def _refine_config(d: dict | None, classes: int) -> RefineConfig | None:
    """A checkpoint's refiner config; one saved before `context`, `flip` or `stages` existed had neither
    part and one stage, one saved before `grow` was per class grew every class's boxes alike, one saved
    before `every_cell` read only the local maxima, and one saved before `mirror` read each box once."""
    if not d:
        return None
    grow = d.get("grow", RefineConfig.grow)
    per_class = [grow] * classes if grow and not isinstance(grow[0], list | tuple) else grow
    old = {
        "context": False,
        "flip": False,
        "stages": 1,
        "every_cell": (False,) * classes,
        "mirror": (False,) * classes,
    }
    return RefineConfig(**{**old, **_tuples(d), "grow": tuple(tuple(g) for g in per_class)})


def _tuples(d: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


# Waymo's TOP LiDAR sits this high in the vehicle frame (its extrinsic z; the frame's origin is about at the
# road): the paper's z slab [-2, 4] m is in the vehicle frame, our grid in the sensor's
WAYMO_TOP_HEIGHT = 2.184


def paper() -> PHiMConfig:
    """The paper's Waymo settings (Sec. 4 and appendix B); the z slab moved into the sensor frame."""
    return PHiMConfig(
        name="paper",
        grid=PolarGridConfig(
            r_bins=468,
            theta_bins=468,
            z_bins=32,
            r_min=0.0,
            r_max=74.88,
            z_min=-2.0 - WAYMO_TOP_HEIGHT,
            z_max=4.0 - WAYMO_TOP_HEIGHT,
        ),
        vfe=VFEConfig(point_features=5, hidden=(128,)),
        backbone=BackboneConfig(d_model=128, frustum_theta_bins=9),
        bev=BEVConfig(x_min=-74.88, x_max=74.88, y_min=-74.88, y_max=74.88, cell=0.32),
        head=HeadConfig(),
        sector_voxels=24576,
    )


def tiny() -> PHiMConfig:
    """Same architecture, sized for real time on a 2-core CPU: a light Mamba (d_state 4, expand 1, one decay
    per channel: `shared_decay`) and the axis + direction yaw code; it reads x, y, z, no intensity (learnt on
    the simulator, intensity did not carry over to real sensors: docs/model.md). (Until 2026-11-23 `tiny` had
    d_state 8, expand 2, a decay per state and the sin/cos yaw code; until 2026-11-25 it read intensity;
    docs/history/model-card.md.)"""
    return PHiMConfig(
        name="tiny",
        grid=PolarGridConfig(
            r_bins=128, theta_bins=256, z_bins=16, r_min=1.0, r_max=52.2, z_min=-3.0, z_max=3.0
        ),
        vfe=VFEConfig(point_features=3, hidden=(32,)),
        backbone=BackboneConfig(
            d_model=32,
            down_strides=(1, 2),
            down_kernels=(3, 3),
            frustum_theta_bins=4,
            mamba=MambaConfig(d_state=4, expand=1, shared_decay=True),
        ),
        bev=BEVConfig(
            x_min=-51.2,
            x_max=51.2,
            y_min=-51.2,
            y_max=51.2,
            cell=0.8,
            layer_nums=(0, 1),
            layer_strides=(2, 2),
            num_filters=(32, 64),
            upsample_strides=(2, 4),
            num_upsample_filters=(32, 32),
        ),
        head=HeadConfig(
            shared_channels=16,
            head_channels=16,
            head_convs=1,
            pre_nms_top_k=1000,
            post_nms_top_k=200,
            heading=HeadingCode.AXIS_DIRECTION,
        ),
    )


CONFIGS = {"paper": paper, "tiny": tiny}


def get_config(name: str) -> PHiMConfig:
    if name not in CONFIGS:
        raise ValueError(f"unknown config {name!r}; expected one of {sorted(CONFIGS)}")
    return CONFIGS[name]()
