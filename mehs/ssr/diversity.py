"""Spectral diversity of a paired dataset's splits (``python -m mehs.ssr.diversity DATASET``).

Works on anything :func:`mehs.ssr.data.load_pairs` lists: a mehs dataset, a folder of pairs,
or a public SSR dataset (ARAD-1K, ICVL, CAVE, …). The figures are those of
:func:`mehs.scenes.diversity.spectral_diversity`, on the ``split`` scenes, with the angle from
each of their pixels to the nearest pixel of the ``reference`` split (what a model trained on
that split has seen). Pixels not resolved above the noise are excluded and counted.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mehs.errors import InputError
from mehs.io.atomic import write_json_atomic
from mehs.scenes.diversity import (draw, figures, format_diversity, merge_records,
                                   noise_angle_for, screen_cube)
from mehs.ssr.data import load_pairs


def _pixels(pairs, per_scene: int, seed: int, min_norm, noise_angle_deg
            ) -> tuple[np.ndarray, dict]:
    """Up to ``per_scene`` resolved, valid pixels of each scene (unit rows, random order)
    and the record of what was excluded (:func:`mehs.scenes.diversity.merge_records`).

    The noise test runs on the whole image (it needs the neighbours), before sampling.
    """
    rng = np.random.default_rng(seed)
    rows, recs = [], []
    for p in pairs:
        data, _ = p.hs_array()
        flat, keep, rec = screen_cube(data, valid=p.valid(data.shape[:2]), min_norm=min_norm,
                                      noise_angle_deg=noise_angle_deg)
        rows.append(draw([(flat, keep)], per_scene, rng))
        recs.append(rec)
    return np.concatenate(rows), merge_records(recs)


def dataset_diversity(dataset: str | Path, *, split: str | None = "test",
                      reference: str | None = "train", per_scene: int = 4000,
                      seed: int = 0, angle_deg: float = 1.0,
                      noise_angle_deg: float | None = None,
                      min_norm: float | None = None) -> dict:
    """Diversity of ``split`` (``None``: every scene), against ``reference`` when it exists.

    Pixels are sampled (``per_scene`` valid pixels of each scene, resolved above its noise,
    see :mod:`mehs.scenes.diversity`) so a large public set costs seconds. Returns the
    figures of :func:`mehs.scenes.diversity.spectral_diversity` (the exclusion counts
    included) plus ``scenes``, ``split``, ``reference``.
    """
    if int(per_scene) < 1:
        raise InputError(f"per_scene must be at least 1, got {per_scene}")
    na = noise_angle_for(angle_deg, noise_angle_deg)
    pairs = load_pairs(dataset, split=split)
    if not len(pairs):
        raise InputError(f"no scene in split {split!r}", dataset)
    x, rec = _pixels(pairs, per_scene, seed, min_norm, na)
    ref, ref_rec = None, {}
    if reference is not None and (load_pairs(dataset).splits or {}).get(reference):
        ref, r = _pixels(load_pairs(dataset, split=reference), per_scene, seed + 1, min_norm, na)
        ref_rec = {f"reference_{k}": v for k, v in r.items()}
    # the scenes' samples are concatenated scene by scene: shuffle, or the clustering and
    # the nearest-pixel angle (which read a prefix) would see the first scenes only
    x = x[np.random.default_rng(seed + 2).permutation(x.shape[0])]
    d = figures(x, ref, angle_deg)
    d.update(noise_angle_deg=na, **rec, **ref_rec)
    d.update({"scenes": len(pairs), "split": split,
              "reference": reference if ref is not None else None})
    return d


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mehs.ssr.diversity", description=__doc__)
    ap.add_argument("dataset")
    ap.add_argument("--split", default="test", help="split to describe, or 'all' (default test)")
    ap.add_argument("--reference", default="train", help="split for the nearest-pixel angle")
    ap.add_argument("--per-scene", type=int, default=4000)
    ap.add_argument("--angle", type=float, default=1.0,
                    help="leader-clustering angle in degrees (default 1)")
    ap.add_argument("--noise-angle", type=float, default=None,
                    help="largest angular noise of a pixel kept, degrees (default angle/2)")
    ap.add_argument("--min-norm", type=float, default=None,
                    help="keep pixels with ‖x‖ ≥ this instead of measuring the noise "
                         "(0: keep every pixel)")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = ap.parse_args(argv)
    split = None if a.split == "all" else a.split
    d = dataset_diversity(a.dataset, split=split, reference=a.reference, per_scene=a.per_scene,
                          angle_deg=a.angle, noise_angle_deg=a.noise_angle,
                          min_norm=a.min_norm)
    print(format_diversity(d, title=f"{a.dataset}: {d['scenes']} scene(s), split {a.split}"
                                     + (f" vs {d['reference']}" if d["reference"] else "")))
    if a.json is not None:
        write_json_atomic(a.json, d)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
