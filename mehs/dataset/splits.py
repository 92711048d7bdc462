"""Train/val/test splits of the passing scenes, reproducible from a seed.

Each scene id is ranked by ``sha256(f"{seed}:{id}")`` and the ranking is cut
at ``round(n·f_train)`` and ``round(n·(f_train+f_val))``. The result depends
only on the set of ids and the seed — not on build order or worker count — and
adding scenes moves few existing ones between splits.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from mehs.errors import InputError
from mehs.io.atomic import write_text_atomic

SPLIT_NAMES = ("train", "val", "test")


def parse_fractions(text: str | tuple[float, ...]) -> tuple[float, float, float]:
    """``"0.7,0.15,0.15"`` → ``(0.7, 0.15, 0.15)``; non-negative, summing to 1 (±1e-6)."""
    try:
        vals = tuple(float(v) for v in (text.split(",") if isinstance(text, str) else text))
    except ValueError:
        raise InputError(f"splits {text!r}: expected three numbers like 0.7,0.15,0.15") from None
    if len(vals) != 3 or any(v < 0 for v in vals) or abs(sum(vals) - 1) > 1e-6:
        raise InputError(f"splits {text!r}: need three non-negative fractions summing to 1")
    return vals  # type: ignore[return-value]


def make_splits(scene_ids: list[str], fractions=(0.7, 0.15, 0.15),
                seed: int = 0) -> dict[str, list[str]]:
    """Assign ``scene_ids`` to ``train``/``val``/``test``; each list sorted by id."""
    f = parse_fractions(fractions)
    ranked = sorted(scene_ids, key=lambda s: (hashlib.sha256(f"{seed}:{s}".encode()).digest(), s))
    n = len(ranked)
    a = round(n * f[0])
    b = max(a, round(n * (f[0] + f[1])))
    parts = (ranked[:a], ranked[a:b], ranked[b:])
    return {name: sorted(p) for name, p in zip(SPLIT_NAMES, parts)}


def pick_holdout(scene_ids: list[str], n: int, seed: int = 0) -> list[str]:
    """``n`` of ``scene_ids`` chosen by the same seeded ranking as :func:`make_splits`
    (sorted by id): the paper's "randomly selected 10 data from the training data as
    validation data" (§3.6.1), reproducible and independent of the listing order."""
    if int(n) < 0:
        raise InputError(f"cannot hold out {n} scenes")
    ranked = sorted(scene_ids, key=lambda s: (hashlib.sha256(f"{seed}:{s}".encode()).digest(), s))
    return sorted(ranked[:int(n)])


def write_split_files(dataset: str | Path, splits: dict[str, list[str]]) -> list[Path]:
    """Write ``splits/<name>.txt`` (one id a line) atomically."""
    return [write_text_atomic(Path(dataset) / "splits" / f"{name}.txt",
                              "".join(f"{s}\n" for s in splits.get(name, [])))
            for name in SPLIT_NAMES]
