"""Which scans and which classes of a data set a command reads (`custom:DIR`, lidar/custom.py): the split
and the class map. Plain Python, so that the command lines' options import no numpy."""

from __future__ import annotations

import enum
from dataclasses import dataclass

from lidar.types import CLASS_NAMES

IGNORE = "IGNORE"  # a class map target: boxes of this class are not targets
ANY = "*"  # a class map source: every class the map does not name


class Split(enum.StrEnum):
    TRAIN = "train"  # phim train
    VAL = "val"  # phim eval, phim diagnose


@dataclass(frozen=True)
class ClassMap:
    """Dataset class name (any case) -> a CLASS_NAMES index, or None (IGNORE: not a target)."""

    entries: tuple[tuple[str, str], ...] = ()  # (dataset name, CLASS_NAMES entry or IGNORE), as given
    ignore_others: bool = False  # `*=IGNORE`: a name not in the map is dropped (else an error)

    def __str__(self) -> str:
        parts = [f"{name}={target}" for name, target in self.entries]
        return ",".join(parts + ([f"{ANY}={IGNORE}"] if self.ignore_others else []))

    def table(self) -> dict[str, int | None]:
        """Lower-case name -> class index or None: CLASS_NAMES themselves, then the entries over them."""
        out: dict[str, int | None] = {name.lower(): i for i, name in enumerate(CLASS_NAMES)}
        for name, target in self.entries:
            out[name.lower()] = None if target == IGNORE else CLASS_NAMES.index(target)
        return out


def parse_class_map(text: str) -> ClassMap:
    """'Car=VEHICLE,Truck=VEHICLE,Misc=IGNORE,*=IGNORE' -> ClassMap ('' : the default); ValueError naming the
    bad entry."""
    entries: list[tuple[str, str]] = []
    ignore_others = False
    targets = (*CLASS_NAMES, IGNORE)
    for item in (p.strip() for p in text.split(",")):
        if not item:
            continue
        name, sep, target = (s.strip() for s in item.partition("="))
        target = target.upper()
        if not sep or not name or target not in targets:
            raise ValueError(
                f"class map entry {item!r}: expected NAME=CLASS with CLASS one of {list(targets)}"
            )
        if any(c.isspace() for c in name):
            raise ValueError(f"class map entry {item!r}: a class name has no spaces (labels split on them)")
        if name == ANY:
            if target != IGNORE:
                raise ValueError(f"class map entry {item!r}: only {ANY}={IGNORE} is allowed for {ANY}")
            ignore_others = True
        elif any(known.lower() == name.lower() for known, _ in entries):
            raise ValueError(f"class map entry {item!r}: {name!r} is mapped twice")
        else:
            entries.append((name, target))
    return ClassMap(tuple(entries), ignore_others)
