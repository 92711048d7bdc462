"""Spectral diversity of a paired dataset's splits (``python -m mehs.ssr.diversity DATASET``).

Works on anything :func:`mehs.ssr.data.load_pairs` lists: a mehs dataset, a folder of pairs,
or a public SSR dataset (ARAD-1K, ICVL, CAVE, …). The figures are those of
:func:`mehs.scenes.diversity.spectral_diversity`, on the ``split`` scenes, with the angle from
each of their pixels to the nearest pixel of the ``reference`` split (what a model trained on
that split has seen).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mehs.scenes.diversity import format_diversity, spectral_diversity
from mehs.ssr.data import load_pairs


def _pixels(pairs, per_scene: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for p in pairs:
        data, _ = p.hs_array()
        flat = data.reshape(-1, data.shape[-1])[p.valid(data.shape[:2]).reshape(-1)]
        if flat.shape[0] > per_scene:
            flat = flat[rng.choice(flat.shape[0], per_scene, replace=False)]
        out.append(np.array(flat, dtype=np.float32))
    return out


def dataset_diversity(dataset: str | Path, *, split: str | None = "test",
                      reference: str | None = "train", per_scene: int = 4000,
                      seed: int = 0) -> dict:
    """Diversity of ``split`` (``None``: every scene), against ``reference`` when it exists.

    Pixels are sampled (``per_scene`` valid pixels of each scene) so a large public set costs
    seconds. Returns the figures of :func:`spectral_diversity` plus ``scenes``.
    """
    pairs = load_pairs(dataset, split=split)
    ref = None
    if reference is not None and (load_pairs(dataset).splits or {}).get(reference):
        ref = _pixels(load_pairs(dataset, split=reference), per_scene, seed + 1)
    d = spectral_diversity(_pixels(pairs, per_scene, seed), ref, seed=seed)
    d.update({"scenes": len(pairs), "split": split, "reference": reference if ref else None})
    return d


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mehs.ssr.diversity", description=__doc__)
    ap.add_argument("dataset")
    ap.add_argument("--split", default="test", help="split to describe, or 'all' (default test)")
    ap.add_argument("--reference", default="train", help="split for the nearest-pixel angle")
    ap.add_argument("--per-scene", type=int, default=4000)
    a = ap.parse_args(argv)
    split = None if a.split == "all" else a.split
    d = dataset_diversity(a.dataset, split=split, reference=a.reference, per_scene=a.per_scene)
    print(format_diversity(d, title=f"{a.dataset}: {d['scenes']} scene(s), split {a.split}"
                                     + (f" vs {d['reference']}" if d["reference"] else "")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
