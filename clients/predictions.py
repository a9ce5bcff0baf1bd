"""The native prediction file: JSON lines, a header then one record per sector sent (see docs/data.md).

A scan's prediction is its record with `last_in_scan: true` (after the scan's last sector the boxes cover
everything the stream's sector buffer holds: the full turn once `context_sectors == sectors_per_turn`).
Boxes are (K, 7) x, y, z (box centre), l, w, h, yaw in the frame the points were sent in (metres, radians).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import numpy as np

FORMAT = "phim.predictions"
VERSION = 1
BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw")


@dataclass(frozen=True)
class PredictionRecord:
    scan: str  # scan name (file name without suffix)
    scan_index: int  # position of the scan in the drive
    seq: int
    sector_index: int
    position: int  # sector's place in its scan's sweep, 0..sectors_per_turn-1
    last_in_scan: bool
    timestamp_ns: int
    points: int  # points sent in this sector
    context_sectors: int
    boxes: np.ndarray  # (K, 7) float32
    scores: np.ndarray  # (K,) float32
    labels: np.ndarray  # (K,) int32
    class_names: tuple[str, ...]  # (K,)
    timings: dict[str, float]  # the server's queue_ms, model_ms, total_ms
    latency_ms: float  # client side, send to answer
    error: dict[str, Any] | None = None  # {"code", "message", "field"} when the server refused the sector

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": "sector",
            **{k: getattr(self, k) for k in ("scan", "scan_index", "seq", "sector_index", "position")},
            **{k: getattr(self, k) for k in ("last_in_scan", "timestamp_ns", "points", "context_sectors")},
            "boxes": np.asarray(self.boxes, dtype=np.float64).round(4).tolist(),
            "scores": np.asarray(self.scores, dtype=np.float64).round(5).tolist(),
            "labels": np.asarray(self.labels).astype(int).tolist(),
            "class_names": list(self.class_names),
            "timings": self.timings,
            "latency_ms": round(self.latency_ms, 3),
            "error": self.error,
        }

    @staticmethod
    def from_json(d: dict[str, Any]) -> PredictionRecord:
        return PredictionRecord(
            **{k: d[k] for k in ("scan", "scan_index", "seq", "sector_index", "position", "last_in_scan")},
            **{
                k: d[k]
                for k in ("timestamp_ns", "points", "context_sectors", "timings", "latency_ms", "error")
            },
            boxes=np.asarray(d["boxes"], dtype=np.float32).reshape(-1, 7),
            scores=np.asarray(d["scores"], dtype=np.float32),
            labels=np.asarray(d["labels"], dtype=np.int32),
            class_names=tuple(d["class_names"]),
        )


class PredictionWriter:
    """Writes the header at open, then one line per record (flushed: a crash keeps what was written)."""

    def __init__(self, path: Path, header: dict[str, Any]):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: IO[str] = self.path.open("w")
        self._line(
            {"kind": "header", "format": FORMAT, "version": VERSION, "box_columns": BOX_COLUMNS, **header}
        )
        self.records = 0

    def _line(self, obj: dict[str, Any]) -> None:
        self._f.write(json.dumps(obj) + "\n")
        self._f.flush()

    def write(self, record: PredictionRecord) -> None:
        self._line(record.to_json())
        self.records += 1

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> PredictionWriter:
        return self

    def __exit__(
        self, et: type[BaseException] | None, e: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def read_predictions(path: Path) -> tuple[dict[str, Any], list[PredictionRecord]]:
    """-> (header, records in file order); ValueError when the file is not a prediction file."""
    lines = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    if not lines or lines[0].get("kind") != "header" or lines[0].get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} file (no header line)")
    if lines[0].get("version") != VERSION:
        raise ValueError(f"{path}: version {lines[0].get('version')}; this reader knows {VERSION}")
    return lines[0], [PredictionRecord.from_json(d) for d in lines[1:] if d.get("kind") == "sector"]


def scan_predictions(records: list[PredictionRecord]) -> dict[str, PredictionRecord]:
    """Each scan's prediction: its last sector's record."""
    return {r.scan: r for r in records if r.last_in_scan}
