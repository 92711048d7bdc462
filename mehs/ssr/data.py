"""Paired HS/RGB sets for SSR evaluation, loaded lazily scene by scene.

Three layouts are accepted by :func:`load_pairs`:

1. A **dataset folder** (format 3 of the working agreement): ``manifest.json``
   lists scenes with ``files`` ``hs`` (ENVI), ``hdr_rgb`` (EXR), ``ldr_rgb``
   (PNG), ``mask`` (PNG) and ``splits``. Only scenes with ``status == "pass"``
   are used unless ``include_failed=True``.
2. A **plain folder of pairs**: ``<stem>.hdr`` (ENVI HS cube) with
   ``<stem>.exr`` (HDR-RGB) and/or ``<stem>.png`` (LDR-RGB) and an optional
   ``<stem>_mask.png``. There are no splits.
3. A **public SSR dataset** folder (ARAD-1K, ARAD/BGU-HS, ICVL, CAVE, KAUST), format
   detected or set by :func:`mehs.ssr.sources.remember_source`: see :mod:`mehs.ssr.sources`.

LDR-RGB is linearised with the sRGB EOTF (IEC 61966-2-1) and divided by the
exposure that made it (``ldr = encode(clip(exposure · hdr))``) so it is on the
HDR-RGB's scale. The exposure is read from the manifest scene entry
(``quality.ldr_exposure`` as ``mehs build`` writes it, else ``rgb.ldr_exposure`` or
``ldr_exposure``); if it is not
recorded and an HDR-RGB exists it is estimated as the ratio of the two over
well-exposed pixels (linear LDR in 0.02..0.9); otherwise it is taken as 1.

Units: a dataset scene's files store ``radiance × quality.radiance_scale`` (a power of two
``mehs build`` picks per scene so that half floats keep their precision; stated in each
file's header as ``mehs radiance scale`` / ``mehsRadianceScale``). :class:`Pair` divides it
out, so that every scene of a set is in the dataset's own unit (DN/ms, or radiance when
calibrated) whatever its ``k``: RMSE, a fixed-scale pre-processing and training pairs would
otherwise mix units that differ by 2^k from scene to scene.

Masks: 8-bit, 0 = valid; bits 1 (saturated in every exposure), 2 (ghost) and
4 (other invalid) exclude a pixel from every metric. Bit 8 (ground truth not resolved
above its own noise: spectrum SNR below 10, :mod:`mehs.dataset.noisefloor`) excludes it
too unless the pairs are loaded with ``score_unresolved=True`` (the paper's protocol:
every pixel the camera measured); masks of datasets built before it lack the bit and
read as before. A scene whose manifest entry records ``quality.noise_model`` also gives
the MRAE's element floor (:meth:`Pair.mrae_floor`).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from mehs.dataset.noisefloor import MASK_UNRESOLVED  # the bit the dataset build sets
from mehs.errors import FormatError, InputError

DATASET_FORMAT = "mehs-dataset/1"
RGB_INPUTS = ("hdr", "ldr")


@lru_cache(maxsize=1)
def _srgb_eotf_lut() -> np.ndarray:
    v = np.arange(256) / 255.0
    lut = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    return lut.astype(np.float32)


def srgb_decode_8bit(img: np.ndarray) -> np.ndarray:
    """8-bit sRGB-encoded values → linear float32 in [0, 1] (sRGB EOTF, IEC 61966-2-1)."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        raise InputError(f"expected an 8-bit image, got {img.dtype}")
    return _srgb_eotf_lut()[img]


def read_png(path: Path, *, gray: bool = False) -> np.ndarray:
    """Read a PNG as uint8 ``(H, W, 3)`` RGB (or ``(H, W)`` if ``gray``)."""
    import cv2

    if not Path(path).is_file():
        raise InputError("no such image file", path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError("not a readable PNG image", path)
    if img.dtype != np.uint8:
        raise FormatError(f"expected 8 bits per channel, got {img.dtype}", path)
    if gray:
        if img.ndim == 3:
            if img.shape[2] == 1 or np.all(img[..., :3] == img[..., :1]):
                return np.ascontiguousarray(img[..., 0])
            raise FormatError("mask must be single channel", path)
        return img
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1])  # OpenCV reads BGR


def read_rgb_exr(path: Path) -> np.ndarray:
    """Read an HDR-RGB OpenEXR as float32 ``(H, W, 3)`` (channels R, G, B), as stored."""
    return _read_rgb_exr(path)[0]


def _read_rgb_exr(path: Path) -> tuple[np.ndarray, float | None]:
    """``(rgb as stored, its mehsRadianceScale or None)``."""
    from mehs.export import parse_radiance_scale
    from mehs.io.exr import read_exr

    img = read_exr(path)
    chans = [c.upper() for c in img.channels]
    try:
        idx = [chans.index(c) for c in ("R", "G", "B")]
    except ValueError:
        raise FormatError(f"HDR-RGB needs channels R, G, B; found {img.channels}", path) from None
    scale = parse_radiance_scale(img.header.get("mehsRadianceScale"), path)
    return np.ascontiguousarray(np.asarray(img.data, dtype=np.float32)[..., idx]), scale


#: ENVI keys that describe the stored values' scale, void once it is divided out
_SCALE_KEYS = ("mehs radiance scale", "data gain values", "data offset values")


@dataclass
class Pair:
    """One scene: ground-truth HS cube and its RGB renderings, loaded on demand."""

    id: str
    hs_path: Path
    hdr_path: Path | None = None
    ldr_path: Path | None = None
    mask_path: Path | None = None
    ldr_exposure: float | None = None
    split: str | None = None
    info: dict[str, Any] = field(default_factory=dict)
    #: the ground truth's band noise model (``quality.noise_model`` of the manifest), or None
    noise_model: dict[str, Any] | None = None
    #: score pixels flagged only as not resolved above the noise (mask bit 8)
    score_unresolved: bool = False
    #: ``quality.radiance_scale`` of the manifest (files store radiance × it), or None
    radiance_scale: float | None = None

    def _scale(self, stated: float | None, path: Path) -> float:
        """The factor ``path`` stores its values multiplied by: its header's, checked against
        the manifest's (a file edited or copied from another build must not be silently
        2^k off its pair), else the manifest's, else 1."""
        if stated is None:
            return 1.0 if self.radiance_scale is None else float(self.radiance_scale)
        if self.radiance_scale is not None and not np.isclose(stated, self.radiance_scale,
                                                              rtol=1e-6, atol=0):
            raise FormatError(f"scene {self.id!r}: the file states radiance scale {stated!r}, "
                              f"manifest.json {self.radiance_scale!r} (files of different "
                              "builds?)", path)
        return float(stated)

    def hs(self):
        """The ground truth as a :class:`~mehs.cube.SpectralCube` in the dataset's unit
        (memory-mapped when it was stored unscaled)."""
        from mehs.export import radiance_scale
        from mehs.io.envi import read_envi

        cube = read_envi(self.hs_path)
        s = self._scale(radiance_scale(cube), self.hs_path)
        self.info["radiance_scale"] = s
        if s == 1.0:
            return cube
        meta = {k: v for k, v in (cube.metadata or {}).items() if k not in _SCALE_KEYS}
        # a power of two: the division is exact, the values are the fused radiance's
        return cube.with_data(np.asarray(cube.data, dtype=np.float32) / np.float32(s),
                              metadata=meta)

    def hs_array(self) -> tuple[np.ndarray, np.ndarray]:
        """``(data float32 (H, W, B), wavelengths (B,))``, checked finite."""
        cube = self.hs()
        data = np.asarray(cube.data, dtype=np.float32)
        if not np.all(np.isfinite(data)):
            raise InputError("ground-truth cube contains NaN or inf", self.hs_path)
        return data, cube.wavelengths

    def hdr_rgb(self) -> np.ndarray:
        """Linear HDR-RGB float32 ``(H, W, 3)`` in the dataset's unit."""
        if self.hdr_path is None:
            raise InputError(f"scene {self.id!r} has no HDR-RGB file", self.hs_path.parent)
        rgb, stated = _read_rgb_exr(self.hdr_path)
        if not np.all(np.isfinite(rgb)):
            raise InputError("HDR-RGB contains NaN or inf", self.hdr_path)
        s = self._scale(stated, self.hdr_path)
        self.info["hdr_rgb_scale"] = s
        return rgb if s == 1.0 else rgb / np.float32(s)

    def ldr_rgb(self) -> np.ndarray:
        """LDR-RGB linearised and brought to the HDR scale, float32 ``(H, W, 3)``."""
        if self.ldr_path is None:
            raise InputError(f"scene {self.id!r} has no LDR-RGB file", self.hs_path.parent)
        lin = srgb_decode_8bit(read_png(self.ldr_path))
        exposure = self.ldr_exposure
        if exposure is not None:
            # metered on the stored HDR-RGB (ldr = encode(exposure · stored)), so the
            # exposure onto the dataset's unit also carries the stored scale
            exposure = exposure * self._ldr_scale()
        elif self.hdr_path is not None:
            exposure = self._estimate_exposure(lin)      # against hdr_rgb(): already unscaled
        if exposure is None or not (np.isfinite(exposure) and exposure > 0):
            exposure = 1.0
        self.info["ldr_exposure_used"] = float(exposure)
        return lin / np.float32(exposure)

    def _ldr_scale(self) -> float:
        """Scale of the HDR-RGB the recorded LDR exposure was metered on."""
        if self.radiance_scale is not None:
            return float(self.radiance_scale)
        if self.hdr_path is not None:
            return self._scale(_read_rgb_exr(self.hdr_path)[1], self.hdr_path)
        return 1.0

    def _estimate_exposure(self, lin: np.ndarray) -> float | None:
        hdr = self.hdr_rgb()
        if hdr.shape != lin.shape:
            return None
        ok = (lin > 0.02) & (lin < 0.9) & (hdr > 0)
        if np.count_nonzero(ok) < 10:
            return None
        return float(lin[ok].sum() / hdr[ok].sum())

    def rgb(self, kind: str) -> np.ndarray:
        """``kind`` = ``"hdr"`` or ``"ldr"`` → linear float32 ``(H, W, 3)``."""
        if kind == "hdr":
            return self.hdr_rgb()
        if kind == "ldr":
            return self.ldr_rgb()
        raise InputError(f"unknown RGB input {kind!r}; use one of {RGB_INPUTS}")

    def has(self, kind: str) -> bool:
        return (self.hdr_path if kind == "hdr" else self.ldr_path) is not None

    def mask(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Dataset mask uint8 ``(H, W)`` (0 = valid); zeros when the scene has none."""
        if self.mask_path is None:
            if shape is None:
                shape = self.hs().shape[:2]
            return np.zeros(shape, dtype=np.uint8)
        m = read_png(self.mask_path, gray=True)
        if shape is not None and m.shape != tuple(shape):
            raise FormatError(f"mask is {m.shape}, the cube is {tuple(shape)}", self.mask_path)
        return m

    def valid(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """Boolean ``(H, W)``: True where the mask is 0 (bit 8 ignored with
        ``score_unresolved``); the pixels bit 8 removes are counted in
        ``info["unresolved_pixels"]``."""
        m = self.mask(shape)
        other = (m & np.uint8(0xFF ^ MASK_UNRESOLVED)) == 0      # no other bit set
        self.info["unresolved_pixels"] = int(np.count_nonzero(other & (m != 0)))
        return other if self.score_unresolved else m == 0

    def mrae_floor(self, gt: np.ndarray) -> np.ndarray | None:
        """MRAE's element floor for the ground truth ``gt (H, W, B)``: 10·σ of its own
        noise (:func:`mehs.dataset.noisefloor.mrae_floor`), float32 like ``gt``; ``None``
        when the scene records no noise model or with ``score_unresolved``."""
        if self.noise_model is None or self.score_unresolved:
            return None
        from mehs.dataset.noisefloor import mrae_floor, scaled

        model = self.noise_model
        # recorded for the stored values; ``gt`` is in the dataset's unit (hs() divided)
        s = self.info.get("radiance_scale", self.radiance_scale) or 1.0
        if s != 1.0:
            model = scaled(model, 1.0 / s)
        try:
            return mrae_floor(gt, model)
        except InputError as exc:
            raise exc.with_path(self.hs_path) from None


class PairSet(list):
    """A list of :class:`Pair` with the folder's ``root``, ``manifest`` (or None) and ``splits``."""

    def __init__(self, pairs, *, root: Path, manifest: dict | None = None,
                 splits: dict[str, list[str]] | None = None):
        super().__init__(pairs)
        self.root = root
        self.manifest = manifest
        self.splits = splits or {}

    @property
    def kind(self) -> str:
        return "dataset" if self.manifest is not None else "pairs"


def _inside(root: Path, rel: str | None, what: str, scene: str) -> Path | None:
    if not rel:
        return None
    p = (root / rel).resolve()
    if root.resolve() not in p.parents:
        raise FormatError(f"scene {scene!r}: {what} path {rel!r} leaves the dataset folder",
                          root / "manifest.json")
    return p


def check_disjoint_splits(splits: dict[str, list], where, how: str = "") -> dict[str, str]:
    """Scene id → its split; :class:`FormatError` naming ``where`` for a scene in two splits
    (it would be trained on and then scored as unseen: a hand-merged manifest or list files)."""
    split_of: dict[str, str] = {}
    for name, ids in splits.items():
        for sid in map(str, ids):
            if split_of.setdefault(sid, name) != name:
                raise FormatError(f"scene {sid!r} is in two splits ({split_of[sid]!r} and "
                                  f"{name!r}){how}; each scene belongs to one split", where)
    return split_of


def _load_manifest(root: Path, *, split: str | None, include_failed: bool,
                   verify: str = "stat", score_unresolved: bool = False) -> PairSet:
    mpath = root / "manifest.json"
    try:
        manifest = json.loads(mpath.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"cannot read the manifest ({exc})", mpath) from None
    if not isinstance(manifest, dict) or not str(manifest.get("format", "")).startswith("mehs-dataset/"):
        raise FormatError(f"not a mehs dataset manifest (format {manifest.get('format') if isinstance(manifest, dict) else None!r})", mpath)
    splits = manifest.get("splits") or {}
    scenes = manifest.get("scenes", [])
    # a hand-edited or damaged manifest must fail here, naming the file, not as an
    # AttributeError deep in the loop below
    if not isinstance(scenes, list) or not all(isinstance(sc, dict) and sc.get("id")
                                               for sc in scenes):
        raise FormatError("'scenes' must be a list of scene objects with an 'id'", mpath)
    if not isinstance(splits, dict) or not all(isinstance(v, list) for v in splits.values()):
        raise FormatError("'splits' must map split names to lists of scene ids", mpath)
    split_of = check_disjoint_splits(splits, mpath)
    if split is not None and split not in splits:
        raise InputError(f"no split {split!r} in the manifest (has {sorted(splits)})", mpath)
    wanted = None if split is None else set(map(str, splits[split]))
    pairs = []
    for sc in scenes:
        sid = str(sc.get("id"))
        if wanted is not None and sid not in wanted:
            continue
        if sc.get("status", "pass") != "pass" and not include_failed:
            continue
        files = sc.get("files") or {}
        if not isinstance(files, dict):
            raise FormatError(f"scene {sid!r}: 'files' must be an object", mpath)
        hs = _inside(root, files.get("hs"), "hs", sid)
        if hs is None:
            raise FormatError(f"scene {sid!r} has no 'hs' file", mpath)
        # a missing file found only when its scene's turn comes would leave an
        # evaluation half written; a stat per file up front is cheap
        for key in ("hs", "hdr_rgb", "ldr_rgb", "mask"):
            f = _inside(root, files.get(key), key, sid)
            if f is not None and not f.is_file():
                raise FormatError(f"scene {sid!r}: {key} file listed in manifest.json is missing", f)
        if verify != "none" and isinstance(sc.get("sha256"), dict):
            from mehs.io.filecheck import verify_files

            run = (sc.get("provenance") or {}).get("run") or {}
            # the recorded hashes (sets made by other tools may record none)
            hashed = {k: v for k, v in files.items() if k in sc["sha256"]}
            verify_files(root, hashed, sc["sha256"], stats=run.get("output_stat"),
                         full=verify == "full", what=f"scene {sid!r}")
        exposure = next((d["ldr_exposure"] for d in (sc.get("quality"), sc.get("rgb"), sc)
                         if isinstance(d, dict) and d.get("ldr_exposure") is not None), None)
        quality = sc.get("quality") if isinstance(sc.get("quality"), dict) else {}
        from mehs.export import parse_radiance_scale

        scale = parse_radiance_scale(quality.get("radiance_scale"),
                                     f"{mpath} (scene {sid!r}, quality.radiance_scale)")
        pairs.append(Pair(
            id=sid, hs_path=hs,
            hdr_path=_inside(root, files.get("hdr_rgb"), "hdr_rgb", sid),
            ldr_path=_inside(root, files.get("ldr_rgb"), "ldr_rgb", sid),
            mask_path=_inside(root, files.get("mask"), "mask", sid),
            ldr_exposure=None if exposure is None else float(exposure),
            split=split_of.get(sid), noise_model=quality.get("noise_model"),
            score_unresolved=bool(score_unresolved), radiance_scale=scale))
    return PairSet(pairs, root=root, manifest=manifest, splits=splits)


def _load_plain(root: Path) -> PairSet:
    pairs = []
    for hdr in sorted(root.glob("*.hdr")):
        stem = hdr.stem
        exr = root / f"{stem}.exr"
        png = root / f"{stem}.png"
        mask = root / f"{stem}_mask.png"
        if not exr.is_file() and not png.is_file():
            continue
        pairs.append(Pair(id=stem, hs_path=hdr,
                          hdr_path=exr if exr.is_file() else None,
                          ldr_path=png if png.is_file() else None,
                          mask_path=mask if mask.is_file() else None))
    return PairSet(pairs, root=root)


def _public_format(root: Path) -> bool:
    """A public SSR dataset (ARAD, ICVL, CAVE, KAUST: :mod:`mehs.ssr.sources`), not pairs?"""
    from mehs.ssr.sources import detect_format, remembered

    if remembered(root):
        return True
    if any(root.glob("*.hdr")):
        return False
    return detect_format(root) is not None


def load_pairs(path: str | Path, *, split: str | None = None,
               include_failed: bool = False, verify: str = "stat",
               score_unresolved: bool = False) -> PairSet:
    """List the paired scenes of a dataset folder or a plain folder of pairs.

    Nothing is read but the manifest: each :class:`Pair` loads its files when
    asked. ``split`` (``"train"``, ``"val"``, ``"test"``) needs a manifest. Files of
    a manifest that records their SHA-256 are verified (``verify``: ``"stat"``
    hashes only files whose size/mtime changed since the build, ``"full"``
    hashes all, ``"none"`` skips), so a damaged scene is never scored.
    ``score_unresolved`` scores the pixels mask bit 8 flags as not resolved above the
    ground truth's noise (the paper's protocol; see the module notes).

    Raises
    ------
    InputError
        The folder does not exist, holds no pairs, or lacks the split.
    FormatError
        The manifest is unreadable or points outside the folder.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputError("no such dataset folder", root)
    if (root / "manifest.json").is_file():
        pairs = _load_manifest(root, split=split, include_failed=include_failed, verify=verify,
                               score_unresolved=score_unresolved)
    elif _public_format(root):
        from mehs.ssr.sources import load_source

        return load_source(root, split=split)
    else:
        if split is not None:
            raise InputError(f"a plain folder of pairs has no split {split!r} (no manifest.json)", root)
        pairs = _load_plain(root)
    if not pairs:
        raise InputError("no paired scenes found (need manifest.json, or <stem>.hdr with "
                         "<stem>.exr and/or <stem>.png)" + (f" in split {split!r}" if split else ""), root)
    return pairs


def nonempty_splits(path: str | Path) -> dict[str, list[str]]:
    """The splits of the dataset at ``path`` that hold scenes (one listing of it)."""
    return {k: v for k, v in (load_pairs(path).splits or {}).items() if v}


def write_index_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    """Write ``rows`` (dicts with the same keys) as CSV, atomically."""
    import io

    from mehs.io.atomic import write_text_atomic

    buf = io.StringIO()
    if rows:
        w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    write_text_atomic(path, buf.getvalue())
