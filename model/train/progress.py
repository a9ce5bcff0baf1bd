"""A progress bar for training (rich), or nothing when disabled."""

from __future__ import annotations

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TextColumn,
    TimeRemainingColumn,
)
from rich.progress import (
    Progress as RichProgress,
)


class Progress:
    def __init__(self, total: int, done: int, enabled: bool):
        self.bar = None
        if enabled:
            self.bar = RichProgress(
                TextColumn("train"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                TextColumn("{task.fields[info]}"),
            )
            self.task = self.bar.add_task("train", total=total, completed=done, info="")
            self.bar.start()

    def update(self, step: int, row: dict[str, float]) -> None:
        if self.bar is not None:
            info = (
                f"loss {row['loss']:.3f} hm {row['heatmap']:.3f} iou {row['mean_iou']:.2f} "
                f"{row['scans_per_s']:.2f} scans/s"
            )
            self.bar.update(self.task, completed=step, info=info)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
