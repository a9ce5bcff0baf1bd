"""How the boxes a model returns are off where they are right (`phim diagnose --matched`): the size bias and
heading flips of matched boxes.

Full-turn predictions (as `phim eval` scores them: field of view and range already applied) with score >=
`score` are matched to the labels of their class, highest score first, each to the unmatched label it
overlaps most at rotated BEV IoU >= `iou`. Per matched pair: the length, width and height error, predicted
minus labelled (metres: negative is too short), the heading error folded to [0, 180] degrees (over 90: the
box points the wrong way round, `flipped`), and how the label was seen: the angle between its heading axis
and the line of sight from the sensor to its centre, folded to [0, 90] degrees (0: seen end-on, its front
or back towards the sensor; 90: side-on, where a box's two ends look alike unless its shape tells them
apart). Along the label's axis, the error of the box's near end (towards the sensor: the end its points
show) and of its far end (where the object hides its back), each positive where the box's end lies beyond
the label's, away from the sensor. Unlike `diagnose` (the detector's regression at the true centre cells),
this is what a user gets, refiner included, and what a team measures on its own labelled sweeps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from model.config import CLASS_NAMES
from model.eval.runner import ScanResult
from model.eval.vehicle_check import iou_bev

# per matched pair: the class, length / width / height error (m), heading error (deg, [0, 180]), view (deg,
# [0, 90]), the label's points, its distance from the sensor (m), near and far end error (m)
PAIR_COLUMNS = ("label", "dl", "dw", "dh", "heading_deg", "view_deg", "points", "range_m", "near", "far")
SIDE_ON_DEG = 45.0  # a label seen at a view angle above this is side-on, else end-on
VIEWS = ("side_on", "end_on")


@dataclass(frozen=True)
class MatchConfig:
    iou: float = 0.5  # rotated BEV IoU of a match (the vehicle check's and the team's)
    score: float = 0.5  # predictions at or above this score (the vehicle check's)


def _fold(angle: np.ndarray, period: float) -> np.ndarray:
    """Angles (radians) -> their distance from 0 modulo `period`, in [0, period / 2], as degrees."""
    wrapped = np.remainder(angle + period / 2, period) - period / 2
    return np.degrees(np.abs(wrapped))


def _ends(p: np.ndarray, t: np.ndarray) -> tuple[float, float]:
    """A box and its label (7,) -> the error of the box's near and far end along the label's axis (m, > 0:
    beyond the label's end, away from the sensor)."""
    axis = np.array([math.cos(t[6]), math.sin(t[6])])
    away = 1.0 if t[:2] @ axis >= 0 else -1.0  # the label's far end lies along away * axis
    shift = away * float((p[:2] - t[:2]) @ axis)  # the box's centre beyond the label's
    turn = p[6] - t[6]  # the box's half extent along the label's axis, less the label's
    grow = abs(p[3] / 2 * math.cos(turn)) + abs(p[4] / 2 * math.sin(turn)) - t[3] / 2
    return shift - grow, shift + grow


def match_scan(r: ScanResult, cfg: MatchConfig) -> np.ndarray:
    """One scan's full-turn prediction against its labels -> (P, len(PAIR_COLUMNS)) float64 matched pairs."""
    pred, truth = r.predictions[-1], r.truths[-1]
    rows = []
    for k in range(len(CLASS_NAMES)):
        keep = (pred.labels == k) & (pred.scores >= cfg.score)
        boxes = np.asarray(pred.boxes, np.float64)[keep]
        boxes = boxes[np.argsort(-pred.scores[keep], kind="stable")]  # (K, 7) highest score first
        of_class = truth.labels == k
        gt = np.asarray(truth.boxes, np.float64)[of_class]  # (M, 7)
        points = truth.num_points[of_class]  # (M,)
        iou = iou_bev(boxes, gt)  # (K, M)
        free = np.ones(len(gt), bool)
        for i in range(len(boxes)):
            cand = np.where(free, iou[i], -1.0)  # (M,)
            j = int(cand.argmax()) if len(gt) else -1
            if j < 0 or cand[j] < cfg.iou:
                continue
            free[j] = False
            p, t = boxes[i], gt[j]
            sight = math.atan2(t[1], t[0])
            rows.append(
                [
                    k,
                    *(p[3:6] - t[3:6]),
                    _fold(np.array(p[6] - t[6]), 2 * math.pi),
                    _fold(np.array(t[6] - sight), math.pi),
                    points[j],
                    math.hypot(t[0], t[1]),
                    *_ends(p, t),
                ]
            )
    return np.asarray(rows, np.float64).reshape(-1, len(PAIR_COLUMNS))


def _share(flags: np.ndarray) -> float | None:
    return float(flags.mean()) if len(flags) else None


def _summary(pairs: np.ndarray, labels: int) -> dict[str, float | None]:
    """Pairs of one group -> counts, median and mean size errors, heading error, flipped shares."""
    col = {name: pairs[:, i] for i, name in enumerate(PAIR_COLUMNS)}
    flipped, side_on = col["heading_deg"] > 90.0, col["view_deg"] > SIDE_ON_DEG
    out: dict[str, float | None] = {"labels": float(labels), "matched": float(len(pairs))}
    for part in ("dl", "dw", "dh", "near", "far"):
        out[f"{part}_median_m"] = float(np.median(col[part]))
        out[f"{part}_mean_m"] = float(col[part].mean())
    for view, sel in zip(VIEWS, (side_on, ~side_on), strict=True):  # is length seen, or guessed?
        out[f"dl_median_{view}_m"] = float(np.median(col["dl"][sel])) if sel.any() else None
    out["heading_median_deg"] = float(np.median(col["heading_deg"]))
    out["flipped"] = _share(flipped)
    out["side_on"] = _share(side_on)
    out["flipped_side_on"] = _share(flipped[side_on])
    out["flipped_end_on"] = _share(flipped[~side_on])
    return out


def box_bias(
    results: Sequence[ScanResult], cfg: MatchConfig | None = None, by_group: bool = False
) -> dict[str, dict[str, float | None]]:
    """Per class name (with `by_group` also per "CLASS, samples subfolder"): labels, matched pairs, median and
    mean l / w / h error (m), the median length error of the side-on and of the end-on, median heading error
    (deg), the shares flipped, seen side-on, and flipped among the side-on and the end-on (None where a group
    has none). Classes with no match are left out."""
    cfg = cfg or MatchConfig()
    groups = [r.name.split("/")[0] if "/" in r.name else "" for r in results]
    pairs = [match_scan(r, cfg) for r in results]
    out: dict[str, dict[str, float | None]] = {}
    for k, name in enumerate(CLASS_NAMES):
        keys: dict[str, str | None] = {name: None}
        if by_group:
            keys |= {f"{name}, {g}": g for g in sorted(set(groups))}
        for key, group in keys.items():
            scans = [i for i, g in enumerate(groups) if group is None or g == group]
            sel = np.concatenate([pairs[i] for i in scans] or [np.zeros((0, len(PAIR_COLUMNS)))])
            sel = sel[sel[:, 0] == k]
            labels = sum(int((results[i].truths[-1].labels == k).sum()) for i in scans)
            if len(sel):
                out[key] = _summary(sel, labels)
    return out


def format_box_bias(d: dict[str, dict[str, float | None]], cfg: MatchConfig | None = None) -> str:
    cfg = cfg or MatchConfig()

    def pct(v: float | None) -> str:
        return "-" if v is None else f"{v:.0%}"

    head = (
        "| group | labels | matched | l / w / h error, median (m) | mean (m) | l error side-on / end-on "
        "| near / far end error, median (m) | heading err | flipped | side-on | flipped side-on / end-on |"
    )
    rows = [head, "|" + "---|" * 11]
    for name, s in d.items():
        med = " / ".join(f"{s[p + '_median_m']:+.2f}" for p in ("dl", "dw", "dh"))
        mean = " / ".join(f"{s[p + '_mean_m']:+.2f}" for p in ("dl", "dw", "dh"))
        views = " / ".join(
            "-" if s[f"dl_median_{v}_m"] is None else f"{s[f'dl_median_{v}_m']:+.2f}" for v in VIEWS
        )
        ends = f"{s['near_median_m']:+.2f} / {s['far_median_m']:+.2f}"
        rows.append(
            f"| {name} | {s['labels']:.0f} | {s['matched']:.0f} | {med} | {mean} | {views} | {ends} "
            f"| {s['heading_median_deg']:.1f} deg | {pct(s['flipped'])} | {pct(s['side_on'])} "
            f"| {pct(s['flipped_side_on'])} / {pct(s['flipped_end_on'])} |"
        )
    note = (
        f"(full-turn boxes scored >= {cfg.score:g} matched at rotated BEV IoU >= {cfg.iou:g}; errors are "
        f"predicted - labelled; near / far end: the box's end towards / away from the sensor along the "
        f"label's axis, + beyond the label's; flipped: heading more than 90 deg off; side-on: the label's "
        f"axis more than {SIDE_ON_DEG:g} deg from the line of sight)"
    )
    return "\n".join(rows) + "\n" + note
