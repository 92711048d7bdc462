"""Public SSR datasets (ARAD-1K, ARAD/BGU-HS, ICVL, CAVE, KAUST, Harvard, KAIST and its 28-band
CASSI cubes) as :class:`PairSet` s.

:func:`load_source` lists a dataset folder's scenes (format detected, or given), with their
splits when the dataset defines them (ARAD-1K ``train_list.txt`` / ``valid_list.txt``, or
``Train_*`` / ``Valid_*`` / ``Test_*`` folders), as :class:`SourcePair` objects that read their
cube on demand through :mod:`mehs.io.ssr_datasets`. ``mehs.ssr.data.load_pairs`` calls it for a
folder that is neither a mehs dataset nor a folder of pairs, so ``mehs evaluate``,
``mehs train-baseline`` and ``mehs train-ssr`` accept these folders directly.

An explicitly chosen format and options (:func:`remember_source`, the CLIs' ``--format``) hold
for that folder for the rest of the process, because the evaluator re-lists a folder per split.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mehs.errors import InputError
from mehs.io.matfile import mat_variable_shapes
from mehs.io.ssr_datasets import (_RGB_EXT, _SPLIT_WORDS, FORMATS, SourceOptions, _cave_pngs,
                                  read_source_cube, read_source_mask)
from mehs.io.ssr_kaist import CASSI28_KEYS, is_kaist_exr
from mehs.ssr.data import Pair, PairSet, check_disjoint_splits, srgb_decode_8bit

_HINTS: dict[Path, tuple[str, SourceOptions]] = {}
_LAST: dict[str, Any] = {}


def remember_source(root: str | Path, fmt: str, opts: SourceOptions = SourceOptions()) -> None:
    """Read ``root`` as ``fmt`` with ``opts`` from now on (this process)."""
    if fmt not in FORMATS:
        raise InputError(f"unknown dataset format {fmt!r}; use one of {', '.join(FORMATS)}")
    _HINTS[Path(root).resolve()] = (fmt, opts)


def remembered(root: str | Path) -> tuple[str, SourceOptions] | None:
    return _HINTS.get(Path(root).resolve())


def _cave_scene_dirs(root: Path) -> list[Path]:
    return sorted({p.parent for p in root.rglob("*_01.png") if len(_cave_pngs(p.parent)) >= 2})


def _is_cassi28(shapes: dict[str, tuple]) -> bool:
    """A CASSI benchmark cube: ``img`` or ``HSI`` of rows × columns × 28 (the variable names
    alone are too common to tell)."""
    return any(len(shapes.get(k, ())) == 3 and shapes[k][2] == 28 for k in CASSI28_KEYS)


def detect_format(root: str | Path) -> str | None:
    """The public format of a dataset folder, or ``None`` (by file types, MATLAB variables and
    EXR channel names)."""
    root = Path(root)
    mats = sorted(root.rglob("*.mat"))
    # a few files, so one truncated download does not hide the format of the rest
    for f in mats[:5]:
        shapes = mat_variable_shapes(f)
        keys = set(shapes)
        if "cube" in keys:
            return "arad1k"
        if "rad" in keys:
            return "arad" if f.stem.upper().startswith(("BGU", "ARAD")) else "icvl"
        if {"ref", "lbl"} <= keys:
            return "harvard"
        if _is_cassi28(shapes):
            return "cassi28"
    if mats:
        return None
    # KAIST by its w<λ>nm channels: RGB EXRs (mehs's own HDR-RGB) are no KAIST scenes
    if any(is_kaist_exr(f) for f in sorted(root.rglob("*.exr"))[:5]):
        return "kaist"
    if next(root.rglob("*.h5"), None) is not None or next(root.rglob("*.hdf5"), None) is not None:
        return "kaust"
    if _cave_scene_dirs(root):
        return "cave"
    return None


def _scene_files(root: Path, fmt: str) -> list[tuple[str, Path]]:
    if fmt == "cave":
        out = []
        for d in _cave_scene_dirs(root):
            sid = d.name[:-3] if d.name.lower().endswith("_ms") else d.name
            out.append((sid, d))
        return out
    pats = {"kaust": ("*.h5", "*.hdf5"), "kaist": ("*.exr",)}.get(fmt, ("*.mat",))
    out = sorted((p.stem, p) for pat in pats for p in root.rglob(pat))
    if fmt == "cassi28":
        # the benchmarks ship their coded aperture beside the cubes (TSA_simu_data/mask.mat,
        # mask_3d_shift.mat): a readable file without a cube variable is no scene; an
        # unreadable one stays listed, so its error is seen
        out = [(sid, p) for sid, p in out
               if not (shapes := mat_variable_shapes(p)) or set(shapes) & set(CASSI28_KEYS)]
    return out


def _rgb_index(root: Path) -> dict[str, Path]:
    idx: dict[str, Path] = {}
    for p in sorted(root.rglob("*")):
        if p.suffix.lower() in _RGB_EXT and p.is_file() and not p.name.lower().endswith(
                tuple(f"_{i:02d}.png" for i in range(1, 41))):
            idx.setdefault(p.stem, p)
    return idx


def _rgb_for(sid: str, idx: dict[str, Path]) -> Path | None:
    for stem in (sid, f"{sid}_clean", f"{sid}_camera", f"{sid}_RGB", f"{sid}_rgb"):
        if stem in idx:
            return idx[stem]
    return None


def _splits(root: Path, entries: list[tuple[str, Path]]) -> dict[str, list[str]]:
    ids = {sid for sid, _ in entries}
    splits: dict[str, list[str]] = {}
    for lst in sorted(root.rglob("*_list.txt")):
        word = lst.stem[:-5].lower()
        name = _SPLIT_WORDS.get(word)
        if name is None:
            continue
        listed = [Path(s.strip()).stem for s in lst.read_text(encoding="utf-8", errors="replace").splitlines()
                  if s.strip()]
        splits.setdefault(name, []).extend(s for s in listed if s in ids)
    if splits:
        out = {k: sorted(set(v)) for k, v in splits.items()}
        check_disjoint_splits(out, root, " by the *_list.txt files")
        return out
    for sid, p in entries:
        name = next((n for part in p.relative_to(root).parts[:-1]
                     for n in [_folder_split(part)] if n), None)
        if name:
            splits.setdefault(name, []).append(sid)
    return {k: sorted(v) for k, v in splits.items()}


def _folder_split(part: str) -> str | None:
    """The split a folder name names, by any of its ``_``/``-``-separated words with
    trailing digits dropped: ``Train_Spec`` and ``NTIRE2020_Train_Spectral`` → train,
    ``NTIRE2020_Validation_Spectral`` and ``NTIRE2018_Validate_Spectral`` → val,
    ``NTIRE2018_Train2_Spectral`` → train (only the first word was looked at, so the NTIRE
    2018/2020 folders had no split at all and their validation scenes were trained on)."""
    for word in re.split(r"[_\-\s.]+", part.lower()):
        name = _SPLIT_WORDS.get(word.rstrip("0123456789"))
        if name:
            return name
    return None


def file_identity(path: Path) -> tuple:
    """What tells one version of a scene's data from another: ``(inode, size, mtime_ns,
    ctime_ns)`` of the file, or of every band PNG of a CAVE scene folder. A cache keyed by
    the path alone served a file re-exported in the same process (a notebook re-run, a
    scene rewritten in place or replaced by rename) as its old content, silently."""
    path = Path(path)
    files = _cave_pngs(path) if path.is_dir() else [path]
    out = []
    for f in files:
        try:
            st = f.stat()
        except OSError:  # gone: the reader says so with the file's name
            out.append((str(f), None))
            continue
        out.append((str(f), st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns))
    return tuple(out)


@dataclass
class SourcePair(Pair):
    """A scene of a public dataset; the cube is read (and the RGB rendered) on demand."""

    fmt: str = "arad1k"
    options: SourceOptions = field(default_factory=SourceOptions)

    def _identity(self) -> tuple:
        ident = file_identity(self.hs_path)
        if self.fmt == "harvard" and self.options.harvard_calib != "none":
            from mehs.io.ssr_harvard import find_calib

            calib = find_calib(self.hs_path)  # read with the cube: its version counts too
            ident += file_identity(calib) if calib is not None else ()
        return ident

    def _read(self):
        key = (str(self.hs_path), self._identity(), self.fmt, self.options)
        if _LAST.get("key") != key:  # one scene cached: evaluate reads the cube, then its RGB
            _LAST.clear()
            _LAST["key"] = key
            _LAST["value"] = read_source_cube(self.fmt, self.hs_path, self.options)
        return _LAST["value"]

    def hs(self):
        from mehs.cube import SpectralCube

        data, wl, info = self._read()
        self.info["source"] = info
        return SpectralCube(data, wl, units="as stored × scale")

    def hs_array(self) -> tuple[np.ndarray, np.ndarray]:
        data, wl, info = self._read()
        self.info["source"] = info
        return data, wl

    def has(self, kind: str) -> bool:
        return kind in ("hdr", "ldr")

    def hdr_rgb(self) -> np.ndarray:
        from mehs.rgb import spectra_to_linear_sRGB

        data, wl, _ = self._read()
        rgb = spectra_to_linear_sRGB(data, wl).astype(np.float32)
        # the same half-float rounding as the EXR that mehs build writes
        return np.minimum(rgb, 65504.0).astype(np.float16).astype(np.float32)

    def ldr_rgb(self) -> np.ndarray:
        from mehs.rgb import ldr_rgb

        hdr = self.hdr_rgb()
        if self.ldr_path is not None:
            from mehs.ssr.data import read_png

            img = read_png(self.ldr_path)
            if self.options.crop is not None:  # the same central crop as the cube
                from mehs.io.ssr_datasets import central_crop

                img = img[central_crop(img.shape, self.options.crop, self.ldr_path)]
            encoding = self.options.rgb_encoding_for(self.fmt)
            lin = (srgb_decode_8bit(img) if encoding == "srgb"
                   else img.astype(np.float32) / np.float32(255.0))
            exposure = self._estimate_exposure(lin) if lin.shape == hdr.shape else None
            self.info.update({"ldr_source": "dataset RGB image", "ldr_encoding": encoding,
                              "ldr_exposure_used": exposure})
            if exposure is None:
                raise InputError(f"the RGB image is {img.shape[:2]} (or too dark to match), the "
                                 f"cube {hdr.shape[:2]}", self.ldr_path)
            return lin / np.float32(exposure)
        ldr, exposure = ldr_rgb(hdr)
        self.info.update({"ldr_source": "mehs.rgb.ldr_rgb of the pseudo-HDR-RGB",
                          "ldr_exposure_used": float(exposure)})
        return srgb_decode_8bit(np.asarray(ldr, dtype=np.uint8)) / np.float32(exposure)

    def mask(self, shape: tuple[int, int] | None = None) -> np.ndarray:
        """The dataset's own mask (Harvard's ``lbl``: moving objects), zeros for the others."""
        if shape is None:
            shape = self.hs_array()[0].shape[:2]
        key = (str(self.hs_path), self._identity(), self.fmt, self.options, tuple(shape))
        if _LAST.get("mask_key") != key:  # one scene cached, as the cube
            m = read_source_mask(self.fmt, self.hs_path, tuple(shape), self.options)
            _LAST["mask_key"], _LAST["mask"] = key, m
        m = _LAST["mask"]
        self.info["masked_pixels"] = int(np.count_nonzero(m))
        return m.copy()


def load_source(root: str | Path, fmt: str | None = None, *, split: str | None = None,
                options: SourceOptions | None = None) -> PairSet:
    """List a public dataset folder as a :class:`PairSet` of :class:`SourcePair`.

    ``fmt`` ``None``: remembered for this folder, else :func:`detect_format`. The set's
    ``manifest`` records the format, options and splits (so a fitted baseline and an evaluation
    say what was read).
    """
    root = Path(root)
    hint = remembered(root)
    opts = options or (hint[1] if hint else SourceOptions())
    fmt = fmt or (hint[0] if hint else None) or detect_format(root)
    if fmt is None:
        raise InputError(f"not a recognised SSR dataset folder (formats: {', '.join(FORMATS)}; "
                         "or give --format)", root)
    if fmt not in FORMATS:
        raise InputError(f"unknown dataset format {fmt!r}; use one of {', '.join(FORMATS)}")
    entries = _scene_files(root, fmt)
    if not entries:
        raise InputError(f"no {fmt} scenes found", root)
    splits = _splits(root, entries)
    if split is not None and split not in splits:
        raise InputError(f"no split {split!r} in this {fmt} dataset (has "
                         f"{sorted(splits) or 'none'})", root)
    wanted = None if split is None else set(splits[split])
    split_of = {sid: name for name, ids in splits.items() for sid in ids}
    rgbs = _rgb_index(root) if fmt in ("arad1k", "arad", "cave") else {}
    pairs = [SourcePair(id=sid, hs_path=p, hdr_path=p, ldr_path=_rgb_for(sid, rgbs),
                        split=split_of.get(sid), fmt=fmt, options=opts)
             for sid, p in entries if wanted is None or sid in wanted]
    manifest = {"format": f"public:{fmt}", "source_format": fmt, "options": opts.record(fmt),
                "splits": splits, "hdr_rgb": "pseudo-HDR-RGB of the cube (half float)",
                "ldr_rgb": "dataset RGB image when shipped, else mehs.rgb.ldr_rgb"}
    return PairSet(pairs, root=root, manifest=manifest, splits=splits)

