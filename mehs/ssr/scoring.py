"""Score SSR models on paired HS/RGB scenes: per-image metrics and their summaries.

:func:`evaluate` runs every model in every requested setting it was trained
for (:mod:`mehs.ssr.protocol`) — input HDR-RGB / LDR-RGB, Reinhard
pre-processing off / on, luminance restoration on / off — on each scene,
computes SAM, MRAE, RMSE and PSNR per image (:mod:`mehs.ssr.metrics`, dataset
masks respected, optional border crop, the MRAE element rule as recorded
options), and summarises them over images (mean ± std, median). The results
folder is written by :mod:`mehs.ssr.results_io`.

Luminance-restoration fallbacks (``X+Y+Z ≤ 0`` of a predicted shape: the
pixel gets a flat spectrum) are counted per image (``restore_fallback``) and
summed per configuration; never silent.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from mehs.errors import InputError
from mehs.ssr.contract import trained_for
from mehs.ssr.data import RGB_INPUTS, PairSet, load_pairs
from mehs.ssr.metrics import METRIC_NAMES, image_metrics, sam_map
from mehs.ssr.preprocess import Preprocessing
from mehs.ssr.protocol import PREPROCESS_CHOICES, model_settings
from mehs.ssr.scoring_models import (defined_settings, evaluation_notes, predict_setting,
                                     resolve_models)


def config_key(input: str, preprocess: str, restore: bool, model: str) -> str:
    """A file-name-safe key of one configuration, e.g. ``hdr-pp_on-lr_on-smits``."""
    return f"{input}-pp_{preprocess}-lr_{'on' if restore else 'off'}-{model}"


def parse_key(key: str) -> tuple[str, str, str, str]:
    """Inverse of :func:`config_key`: ``(input, "on"/"off", "on"/"off", model)``."""
    inp, pp, lr, model = key.split("-", 3)
    return inp, pp.split("_", 1)[1], lr.split("_", 1)[1], model


def _as_tuple(v, allowed: Sequence, what: str) -> tuple:
    if isinstance(v, (str, bool)):
        v = [v]
    out = []
    for x in v:
        if isinstance(x, str) and x in ("both", "all"):
            out.extend(allowed)
            continue
        if isinstance(x, bool) and what == "preprocess":
            x = "on" if x else "off"
        if x not in allowed:
            raise InputError(f"{what} must be among {list(allowed)}, got {x!r}")
        out.append(x)
    return tuple(dict.fromkeys(out))


def _restore_tuple(restore) -> tuple[bool, ...]:
    if isinstance(restore, str):
        if restore != "both":
            raise InputError(f"restore must be True, False or 'both', got {restore!r}")
        return (True, False)
    if isinstance(restore, bool):
        return (restore,)
    return tuple(dict.fromkeys(bool(r) for r in restore))


def _preview(rgb: np.ndarray) -> np.ndarray:
    """uint8 sRGB preview of linear HDR RGB: median luminance → 0.18, Reinhard on luminance."""
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    pos = lum[lum > 0]
    key = float(np.median(pos)) if pos.size else 1.0
    L = lum * np.float32(0.18 / key)
    scale = np.where(L > 0, 1 / (1 + L), 0).astype(np.float32) * np.float32(0.18 / key)
    x = np.clip(rgb * scale[..., None], 0, 1)
    enc = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(enc * 255).astype(np.uint8)


def _pick_pixels(gt: np.ndarray, valid: np.ndarray, k: int = 4, seed: int = 0) -> np.ndarray:
    """Pixels for the spectra figure: darkest, median, brightest valid, and a random one."""
    lum = gt.sum(-1)
    idx = np.flatnonzero(valid.reshape(-1) & (lum.reshape(-1) > 0))
    if idx.size == 0:
        return np.zeros((0, 2), dtype=int)
    order = idx[np.argsort(lum.reshape(-1)[idx], kind="stable")]
    rng = np.random.default_rng(seed)
    pick = [order[0], order[len(order) // 2], order[-1], rng.choice(order)][:k]
    pick = list(dict.fromkeys(int(p) for p in pick))
    return np.stack(np.unravel_index(pick, gt.shape[:2]), 1)


def parse_pixels(specs: Iterable[str] | str | None) -> dict[str, list[tuple[int, int]]]:
    """``["s01:10,20", "s01:3,4"]`` (or one string, ``;``-separated) → ``{"s01": [(10, 20), (3, 4)]}``."""
    if not specs:
        return {}
    if isinstance(specs, str):
        specs = [s for s in specs.split(";") if s.strip()]
    out: dict[str, list[tuple[int, int]]] = {}
    for s in specs:
        scene, sep, rc = str(s).strip().rpartition(":")
        try:
            r, c = (int(v) for v in rc.split(","))
        except ValueError:
            r = c = -1
        if not sep or not scene or r < 0 or c < 0:
            raise InputError(f"pixel {s!r} must be SCENE:ROW,COL with ROW, COL ≥ 0")
        out.setdefault(scene, []).append((r, c))
    return out


def mrae_band_mask(wl: np.ndarray, band_range) -> np.ndarray | None:
    """Bool ``(B,)`` of the bands inside ``band_range = (lo, hi)`` nm, or ``None`` for all."""
    if band_range is None:
        return None
    lo, hi = (float(v) for v in band_range)
    m = (np.asarray(wl) >= lo - 0.01) & (np.asarray(wl) <= hi + 0.01)
    if not m.any():
        raise InputError(f"MRAE band range {lo:g}–{hi:g} nm contains none of the dataset's bands")
    return m


@dataclass
class EvaluationResult:
    """What :func:`evaluate` computed; ``out`` is the results folder (or None)."""

    rows: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    config: dict[str, Any]
    models: list[dict[str, Any]]
    timing: list[dict[str, Any]] | None = None
    skipped: list[dict[str, Any]] = field(default_factory=list)
    figures: list[str] = field(default_factory=list)
    out: Path | None = None

    def tables(self, fmt: str = "markdown", metrics: Sequence[str] = ("sam", "mrae")) -> str:
        from mehs.ssr.results_io import format_tables

        return format_tables(self.summary, self.config, fmt=fmt, metrics=metrics,
                             timing=self.timing)


def _scored_count(flags: np.ndarray | None, valid: np.ndarray | None, crop: int) -> int | None:
    """How many of the flagged pixels ``(H, W)`` lie in the region the metrics score (the
    border crop and the valid mask of :func:`mehs.ssr.metrics.image_metrics`), so that a
    count and ``n_pixels`` share one denominator; ``None`` for no flags."""
    if flags is None:
        return None
    flags = np.asarray(flags, dtype=bool)
    if valid is not None:
        flags = flags & np.asarray(valid, dtype=bool)
    if crop:
        flags = flags[crop:-crop, crop:-crop]
    return int(np.count_nonzero(flags))


def evaluate(dataset: str | Path | PairSet, models: Iterable | str, *,
             preprocess: Sequence[str] | str = ("off", "on"),
             inputs: Sequence[str] | str = ("hdr",),
             restore: bool | Sequence[bool] | str = True,
             crop: int = 0, split: str | None = None, out: str | Path | None = None,
             figures: int = 2, timing: bool = False,
             timing_shape: tuple[int, int] = (1024, 2048),
             seed: int = 0, progress: bool = False,
             preprocessing: Preprocessing | None = None, fixed_preprocess: bool = False,
             pixels: Iterable[str] | str | None = None,
             mrae_threshold: float = 0.0, mrae_relative: bool = False,
             mrae_bands: tuple[float, float] | None = None,
             timing_devices: Sequence[str] = ("cpu", "cuda"),
             score_unresolved: bool = False) -> EvaluationResult:
    """Evaluate ``models`` on ``dataset``, each in the settings it was trained for.

    Parameters
    ----------
    dataset
        A dataset folder, a plain folder of pairs, or a :class:`PairSet`.
    models
        Model specs (see :func:`mehs.ssr.models.load_model`; ``NAME=SPEC`` names
        the row) or model objects; a comma-separated string is split. A bare
        ``"regression"`` is fitted on the train split once per requested
        pre-processing setting.
    preprocess
        ``"off"``, ``"on"`` or ``"both"`` (or a sequence of them).
    inputs
        ``"hdr"``, ``"ldr"`` or both.
    restore
        Luminance restoration for models whose output allows both: ``True``,
        ``False`` or ``"both"``. Shape models are always restored, end-to-end
        ones never (their setting is added when absent).
    crop
        Border (pixels) removed on every side before scoring.
    split
        Manifest split to score, ``None`` for every scene, or ``"auto"`` (the
        test split if there is a non-empty one, else the val split, else every scene).
    out
        Results folder to write (see :mod:`mehs.ssr.results_io`); ``None`` writes nothing.
    figures
        How many scenes keep per-pixel SAM maps and spectra for the report
        (``-1``: all).
    timing
        Also time each model on a ``timing_shape`` image (paper Table 5), on
        each of ``timing_devices`` a model can run on.
    preprocessing
        The :class:`Preprocessing` for fitted-here regressions and for fixed
        baselines scored with pre-processing (default: Reinhard, key 0.18).
    fixed_preprocess
        Also score fixed baselines (Smits, Mallett) with pre-processing.
    pixels
        Extra spectra for the report: ``"SCENE:ROW,COL"`` strings.
    mrae_threshold, mrae_relative, mrae_bands
        MRAE element rule: elements with ``y > threshold`` (× the image's
        ground-truth maximum when ``mrae_relative``) inside ``mrae_bands =
        (lo, hi)`` nm; recorded in the results.
    score_unresolved
        Also score the pixels a mehs dataset's mask flags (bit 8) as not resolved above
        the ground truth's own noise, and drop the MRAE's element floor (10σ of that
        noise): the paper's protocol, every measured pixel. By default they are left out
        and counted (``unresolved_pixels``, ``mrae_floor_excluded``).
    """
    if int(crop) < 0:  # image_metrics checks it too, but only once scoring has begun
        raise InputError(f"crop must be ≥ 0, got {crop}")
    if not (np.isfinite(mrae_threshold) and mrae_threshold >= 0):
        raise InputError(f"MRAE threshold must be a number ≥ 0, got {mrae_threshold}")
    if out is not None:
        from mehs.io.atomic import check_output_dir

        # before the scoring, not after; never inside the dataset (a rebuild of a scene
        # folder deletes what it does not know, results included)
        check_output_dir(out, inputs=[] if isinstance(dataset, PairSet) else [dataset])
    default_pp = preprocessing or Preprocessing()
    pp = _as_tuple(preprocess, PREPROCESS_CHOICES, "preprocess")
    ins = _as_tuple(inputs, RGB_INPUTS, "input")
    rs_req = _restore_tuple(restore)
    want_pix = parse_pixels(pixels)
    all_pairs = (dataset if isinstance(dataset, PairSet)
                 else load_pairs(dataset, score_unresolved=score_unresolved))
    if split == "auto":
        # no test split: the val split is the held-out one (ARAD-1K / NTIRE: the official
        # validation list, the paper's test set, §3.6.1); "all" would score training scenes
        split = next((k for k in ("test", "val") if (all_pairs.splits or {}).get(k)), None)
    pairs = (all_pairs if split is None
             else load_pairs(all_pairs.root, split=split, score_unresolved=score_unresolved))
    if score_unresolved:
        # a PairSet given by the caller keeps its own setting otherwise
        for pair in pairs:
            pair.score_unresolved = True
    unknown = sorted(set(want_pix) - {p.id for p in pairs})
    if unknown:
        raise InputError(f"--pixels names scene(s) {unknown} not among the scored scenes", pairs.root)
    resolved = resolve_models(models, all_pairs, seed=seed, pp=pp, ins=ins, default_pp=default_pp)
    plans = [(model, name, defined_settings(model, model_settings(
        model, ins, pp, rs_req, fixed_preprocess=fixed_preprocess))) for model, name, _ in resolved]
    rs = tuple(dict.fromkeys(r for _, _, st in plans for _, _, r in st)) or rs_req
    undefined = ([name for model, name, _ in resolved if not trained_for(model).declared]
                 if "on" in pp and False in rs_req else [])
    if not any(st for _, _, st in plans):
        notes = evaluation_notes(resolved, ins, pp, rs_req, fixed_preprocess, undefined)
        raise InputError("no model was trained for the requested settings (input "
                         f"{'/'.join(ins)}, pre-processing {'/'.join(pp)}): " + "; ".join(notes) +
                         " — use --preprocess both, or --fixed-preprocess for fixed baselines")
    rule = {"threshold": float(mrae_threshold), "relative": bool(mrae_relative),
            "band_range": None if mrae_bands is None else [float(v) for v in mrae_bands],
            "score_unresolved": bool(score_unresolved)}

    rows: list[dict[str, Any]] = []
    skipped: list[dict[str, Any]] = []
    band_acc: dict[str, list] = {}
    fig_ids: list[str] = []
    fig_pending: list[tuple[Path, dict[str, Any]]] = []
    fig_dir = None if out is None else Path(out) / "figures"
    it = pairs
    if progress:
        from tqdm import tqdm
        it = tqdm(pairs, desc="evaluate", unit="scene")
    for i_scene, pair in enumerate(it):
        gt, wl = pair.hs_array()
        if crop and min(gt.shape[:2]) <= 2 * int(crop):  # before any model runs, naming the scene
            raise InputError(f"--crop {crop} leaves nothing of scene {pair.id!r} "
                             f"({gt.shape[0]}×{gt.shape[1]} pixels)", pair.hs_path)
        valid = pair.valid(gt.shape[:2])
        unresolved = None if pair.score_unresolved else pair.info.get("unresolved_pixels")
        # an element whose truth is within 10 sigma of its own noise measures that noise
        floor = pair.mrae_floor(gt)
        bmask = mrae_band_mask(wl, mrae_bands)
        want_fig = fig_dir is not None and (figures < 0 or len(fig_ids) < figures
                                            or pair.id in want_pix)
        fig: dict[str, Any] = {}
        if want_fig:
            pix = _pick_pixels(gt, valid, seed=seed + i_scene)
            user = np.array(want_pix.get(pair.id, []), dtype=int).reshape(-1, 2)
            if user.size and ((user[:, 0] >= gt.shape[0]) | (user[:, 1] >= gt.shape[1])).any():
                raise InputError(f"--pixels {pair.id}: a pixel lies outside the "
                                 f"{gt.shape[0]}×{gt.shape[1]} image", pair.hs_path)
            pix = np.concatenate([user, pix]) if user.size else pix
            fig = {"pixels": pix, "gt": gt[pix[:, 0], pix[:, 1]], "wavelengths": wl,
                   "n_user_pixels": np.array(len(user))}
        keys: list[str] = []
        for inp in ins:
            if not pair.has(inp):
                skipped.append({"scene": pair.id, "input": inp, "reason": f"no {inp.upper()}-RGB file"})
                continue
            rgb = pair.rgb(inp)
            if rgb.shape[:2] != gt.shape[:2]:
                raise InputError(f"{inp.upper()}-RGB is {rgb.shape[:2]}, the cube is {gt.shape[:2]}",
                                 pair.hdr_path if inp == "hdr" else pair.ldr_path)
            if want_fig and "preview" not in fig:
                fig["preview"] = _preview(rgb)
            for model, name, settings in plans:
                tf = trained_for(model)
                for s_inp, p, r in settings:
                    if s_inp != inp:
                        continue
                    t0 = time.perf_counter()
                    pred, st = predict_setting(model, tf, rgb, p, r, default_pp, wl)
                    dt = time.perf_counter() - t0
                    m = image_metrics(pred, gt, valid=valid, crop=crop,
                                      mrae_threshold=mrae_threshold, mrae_relative=mrae_relative,
                                      mrae_band_mask=bmask, mrae_floor=floor)
                    key = config_key(inp, p, r, name)
                    band_acc.setdefault(key, []).append(m.pop("band_mrae"))
                    rows.append({"scene": pair.id, "input": inp, "preprocess": p, "restore": r,
                                 "model": name, **m, "unresolved_pixels": unresolved,
                                 "restore_fallback": _scored_count(st["restore_fallback_mask"],
                                                                   valid, crop),
                                 "seconds": dt})
                    if want_fig:
                        smap = sam_map(pred, gt)
                        smap[~valid] = np.nan
                        fig[f"sam_{key}"] = smap.astype(np.float16)
                        fig[f"pred_{key}"] = pred[fig["pixels"][:, 0], fig["pixels"][:, 1]]
                        keys.append(key)
        if want_fig and keys:
            fig["keys"] = np.array(json.dumps(keys))
            fig["scene"] = np.array(pair.id)
            # written with the results only once every scene has been scored: a bad
            # scene half-way must not leave a results folder that looks started
            fig_pending.append((fig_dir / f"{pair.id}.npz", fig))
            fig_ids.append(pair.id)

    summary = summarise(rows, band_acc)
    outputs = {n: trained_for(m).output for m, n, _ in resolved}
    for s in summary:  # the model's own restoration setting: rows are labelled by it
        s["natural"] = outputs.get(s["model"]) != "spectra"
    config = {"preprocess": list(pp), "inputs": list(ins), "restore": list(rs), "crop": crop,
              "split": split, "n_scenes": len(pairs), "seed": seed,
              "preprocessing": default_pp.to_dict(), "fixed_preprocess": bool(fixed_preprocess),
              "mrae_rule": rule, "pixels": {k: [list(v) for v in vs] for k, vs in want_pix.items()},
              "notes": evaluation_notes(resolved, ins, pp, rs, fixed_preprocess, undefined)}
    fitted = [n for _, n, d in resolved if d.startswith("fitted on the train split")]
    if fitted and split not in ("test", "val"):
        config["notes"].append(f"{', '.join(dict.fromkeys(fitted))} fitted on the train split "
                               f"and scored on split {split or 'all'}: the scores include "
                               f"training scenes")
    fb = [s for s in summary if s.get("restore_fallback")]
    for s in fb:
        config["notes"].append(
            f"{s['model']} ({s['input'].upper()}, pre-proc. {s['preprocess']}): luminance "
            f"restoration fell back to a flat spectrum (X+Y+Z ≤ 0) at {s['restore_fallback']} "
            f"pixels ({100 * s['restore_fallback_fraction']:.1f} % of those scored)")
    model_info = []
    for m, n, d in resolved:
        tf = trained_for(m)
        model_info.append({"name": n, "description": d, "trained_for": tf.to_dict(),
                           "trained_for_label": tf.label(),
                           "wavelengths": np.asarray(m.wavelengths, dtype=float).tolist()})
    tim = None
    if timing:
        seen: dict[str, Any] = {}
        for m, n, _ in resolved:
            seen.setdefault(n, m)  # one timing per row (the regression fits cost the same)
        from mehs.ssr.timing import time_models

        tim = time_models(list((m, n) for n, m in seen.items()), shape=timing_shape, seed=seed,
                          devices=timing_devices)
    res = EvaluationResult(rows=rows, summary=summary, config=config, models=model_info,
                           timing=tim, skipped=skipped, figures=fig_ids)
    if out is not None:
        from mehs.io.atomic import unlink_durable
        from mehs.ssr.results_io import write_npz, write_results

        # evaluation.json is the folder's commit point (written last by write_results): gone
        # before this run's first file replaces an earlier run's figure, so that a kill now
        # leaves no evaluation.json listing figures it did not make (killed while scoring,
        # the earlier results stay whole)
        unlink_durable(Path(out) / "evaluation.json")
        for path, fig in fig_pending:
            write_npz(path, fig)
        res.out = write_results(res, out, dataset=str(all_pairs.root))
    return res


def _spread(vals: list[float]) -> dict[str, float | None]:
    if not vals:
        return {"mean": None, "std": None, "median": None}
    a = np.asarray(vals, dtype=np.float64)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if a.size > 1 else 0.0,
            "median": float(np.median(a))}


def summarise(rows: list[dict[str, Any]], band_acc: dict[str, list] | None = None) -> list[dict[str, Any]]:
    """Summarise per-image rows into one entry per configuration.

    Per metric: ``<m>`` (mean over the images where it is defined), ``<m>_std``
    (sample std), ``<m>_median``, ``<m>_undefined``; never NaN. Also the excluded
    counts, ``restore_fallback`` (sum; ``None`` if unknown for every image) and
    its fraction of the scored pixels, and ``band_mrae`` (per band, mean over images).
    """
    groups: dict[tuple, list] = {}
    for r in rows:
        groups.setdefault((r["input"], r["preprocess"], r["restore"], r["model"]), []).append(r)
    out = []
    for (inp, p, rs, name), rs_rows in groups.items():
        s: dict[str, Any] = {"input": inp, "preprocess": p, "restore": rs, "model": name,
                             "n_images": len(rs_rows)}
        for k in METRIC_NAMES:
            vals = [r[k] for r in rs_rows if r.get(k) is not None and np.isfinite(r[k])]
            sp = _spread(vals)
            s[k], s[f"{k}_std"], s[f"{k}_median"] = sp["mean"], sp["std"], sp["median"]
            s[f"{k}_undefined"] = len(rs_rows) - len(vals)
        s["sam_excluded"] = int(sum(r.get("sam_excluded", 0) for r in rs_rows))
        s["mrae_excluded"] = int(sum(r.get("mrae_excluded", 0) for r in rs_rows))
        s["mrae_floor_excluded"] = int(sum(r.get("mrae_floor_excluded", 0) for r in rs_rows))
        s["unresolved_pixels"] = int(sum(r.get("unresolved_pixels") or 0 for r in rs_rows))
        fbs = [r.get("restore_fallback") for r in rs_rows]
        known = [f for f in fbs if f is not None]
        s["restore_fallback"] = int(sum(known)) if known else None
        npix = sum(r.get("n_pixels", 0) for r, f in zip(rs_rows, fbs) if f is not None)
        s["restore_fallback_fraction"] = (s["restore_fallback"] / npix) if known and npix else None
        s["seconds_per_image"] = float(np.mean([r["seconds"] for r in rs_rows]))
        key = config_key(inp, p, rs, name)
        if band_acc and key in band_acc:
            bands = np.array([[np.nan if v is None else v for v in b] for b in band_acc[key]],
                             dtype=float)
            cnt = np.isfinite(bands).sum(0)
            with np.errstate(invalid="ignore"):
                mean = np.nansum(bands, 0) / np.maximum(cnt, 1)
            s["band_mrae"] = [float(v) if c else None for v, c in zip(mean, cnt)]
        out.append(s)
    return out
