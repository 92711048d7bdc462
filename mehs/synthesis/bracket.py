"""A bracket of exposures of one scene, loaded from a scene folder or Specim IQ folders.

The raw cubes stay memory-mapped; only the one-line dark/white references are
read into memory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError


@dataclass
class Bracket:
    """Exposures of one scene, shortest first.

    Attributes
    ----------
    exposures
        Raw DN cubes ``(lines, samples, bands)`` (usually uint16 memmaps).
    darks, white
        Per exposure float32 ``(samples, bands)`` dark / white reference (mean of
        the reference lines), or None. A white recorded at another integration
        time or over its own dark (Specim ``WHITEDARKREF``) is given as this
        exposure would have recorded it over ``darks``.
    times_ms
        float64 ``(P,)`` integration times, ascending.
    wavelengths
        float64 ``(bands,)`` nm.
    bit_depth
        ADC bits (12 for a Specim IQ).
    source
        The scene folder (or the first Specim folder).
    truth
        Ground-truth radiance of a simulated scene, or None.
    metadata
        ``scene.json`` (scene folder) or per-exposure Specim metadata.
    """

    exposures: list[SpectralCube]
    darks: list[np.ndarray | None]
    white: list[np.ndarray | None]
    times_ms: np.ndarray
    wavelengths: np.ndarray
    bit_depth: int = 12
    source: Path | None = None
    truth: SpectralCube | None = None
    metadata: dict[str, Any] = field(default_factory=dict)
    #: the SHA-256 check of the scene's files still running (``load_bracket(...,
    #: defer_verify=True)``), or None; :meth:`check_files` waits for it
    file_check: Any = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        validate_bracket(self)

    def check_files(self) -> None:
        """Wait for a deferred file check; :class:`FormatError` naming a file that failed it.

        :func:`mehs.synthesis.fuse.fuse_bracket` calls it before it returns, and
        when it fails (a damaged file is the better explanation of the failure).
        """
        if self.file_check is not None:
            self.file_check.result()
            self.file_check = None

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.exposures[0].shape

    @property
    def sensor(self) -> dict[str, Any]:
        """Sensor parameters recorded in ``scene.json`` (``device.sensor``), if any."""
        dev = self.metadata.get("device") or {}
        s = dev.get("sensor") if isinstance(dev, dict) else None
        return s if isinstance(s, dict) else {}


def validate_bracket(b: Bracket) -> None:
    """Check a bracket; sort it by time. Raises :class:`InputError` naming ``b.source``."""
    src = b.source
    P = len(b.exposures)
    if P < 2:
        raise InputError(f"a bracket needs at least 2 exposures, got {P}", src)
    t = np.asarray(b.times_ms, dtype=np.float64).reshape(-1)
    if t.size != P:
        raise InputError(f"{t.size} exposure times for {P} exposures", src)
    if not np.all(np.isfinite(t) & (t > 0)):
        raise InputError(f"exposure times must be positive, got {t.tolist()} ms", src)
    if len(set(t.tolist())) != P:     # not np.unique: its first call imports numpy.ma (15 ms)
        raise InputError(f"exposure times must be distinct, got {t.tolist()} ms", src)
    shape = b.exposures[0].shape
    wl = b.exposures[0].wavelengths
    for k, e in enumerate(b.exposures):
        where = e.source or src
        if e.shape != shape:
            raise InputError(f"exposure shapes differ: {e.shape} vs {shape}", where)
        if e.wavelengths.shape != wl.shape or not np.allclose(e.wavelengths, wl, rtol=0, atol=1e-3):
            raise InputError("exposure wavelengths differ from the first exposure's", where)
        if np.issubdtype(e.data.dtype, np.floating):
            # cheap, chunked check: a NaN in a raw cube is a broken file
            for l0 in range(0, e.lines, 64):
                if not np.all(np.isfinite(e.data[l0:l0 + 64])):
                    raise InputError("raw cube contains NaN or inf", where)
    for name, refs in (("dark", b.darks), ("white", b.white)):
        if len(refs) != P:
            raise InputError(f"{len(refs)} {name} references for {P} exposures", src)
        for r in refs:
            if r is not None and (r.shape != shape[1:] or not np.all(np.isfinite(r))):
                raise InputError(f"{name} reference must be finite with shape {shape[1:]}, "
                                 f"got {r.shape}", src)
    order = np.argsort(t, kind="stable")
    b.exposures = [b.exposures[i] for i in order]
    b.darks = [b.darks[i] for i in order]
    b.white = [b.white[i] for i in order]
    b.times_ms = t[order]
    b.wavelengths = np.asarray(wl, dtype=np.float64)
    if not 8 <= int(b.bit_depth) <= 16:
        raise InputError(f"bit depth must be 8..16, got {b.bit_depth}", src)


def _ref_mean(ref: SpectralCube | None) -> np.ndarray | None:
    if ref is None:
        return None
    return np.asarray(ref.data, dtype=np.float64).mean(axis=0).astype(np.float32)


def _same_time(a: float, b: float) -> bool:
    """Two integration times (ms) the same within a header's printed precision (0.1 %)."""
    return bool(np.isclose(a, b, rtol=1e-3, atol=0))


def _dark_line(cap, folder: Path) -> np.ndarray | None:
    """``cap``'s dark reference line, refused when recorded at another integration time."""
    d, t = cap.darkref, cap.raw.integration_time_ms
    if d is not None and d.integration_time_ms is not None and t is not None \
            and not _same_time(d.integration_time_ms, t):
        # dark current grows with time: another time's dark shifts every subtracted DN
        raise FormatError(f"dark reference recorded at {d.integration_time_ms:g} ms, the capture "
                          f"at {t:g} ms; a dark must be taken at its exposure's integration "
                          "time", d.source or folder)
    return _ref_mean(d)


def _white_line(cap, t_ms: float, dark: np.ndarray | None, full_dn: int,
                folder: Path) -> np.ndarray | None:
    """``cap``'s white reference line as exposure ``t_ms`` with ``dark`` would have recorded it.

    Users of :attr:`Bracket.white` take ``(white - dark) / t`` per exposure. A
    pre-set Specim IQ white is recorded before the capture, possibly at another
    integration time, with its own dark (``WHITEDARKREF``), so its
    dark-subtracted signal is scaled by ``t_ms / t_white`` onto the capture's
    dark (a linear sensor, as the IQ's own reflectance ``(S-D)/(W-WD)·t_W/t_S``
    assumes). Columns saturated in the white stay at ``full_dn`` (saturated).
    """
    w = _ref_mean(cap.whiteref)
    if w is None:
        return None
    wd = cap.whitedarkref
    tw = cap.whiteref.integration_time_ms
    if wd is not None and wd.integration_time_ms is not None:
        if tw is None:
            tw = wd.integration_time_ms
        elif not _same_time(wd.integration_time_ms, tw):
            raise FormatError(f"white dark reference recorded at {wd.integration_time_ms:g} ms, "
                              f"the white reference at {tw:g} ms; it must be the white's own "
                              "dark", wd.source or folder)
    if tw is None:
        tw = t_ms
    if wd is None and _same_time(tw, t_ms):
        return w
    d = np.zeros_like(w) if dark is None else dark.astype(np.float64)
    w_dark = d if wd is None else _ref_mean(wd).astype(np.float64)
    out = d + (w.astype(np.float64) - w_dark) * (float(t_ms) / float(tw))
    out = np.where(w >= 0.98 * full_dn, float(full_dn), out)
    return out.astype(np.float32)


def _guess_bit_depth(cube: SpectralCube, meta: dict) -> int:
    for key in ("bit_depth", "bit depth", "data_bits"):
        v = meta.get(key) or cube.metadata.get(key)
        if v is not None:
            try:
                return int(v)
            except (TypeError, ValueError):
                pass
    if cube.data.dtype == np.uint8:
        return 8
    return 12 if np.issubdtype(cube.data.dtype, np.integer) and cube.data.dtype.itemsize == 2 \
        and int(np.max(cube.data[:: max(1, cube.lines // 16)])) <= 4095 else 16


def load_bracket(path_or_paths: str | Path | Sequence[str | Path], *, verify: str = "sha256",
                 bit_depth: int | None = None, allow_partial: bool = False,
                 defer_verify: bool = False) -> Bracket:
    """Load a bracket from a scene folder (``scene.json``) or a list of Specim IQ folders.

    Parameters
    ----------
    path_or_paths
        A scene folder (format ``mehs-scene/1``; only exposures with status
        ``"complete"`` are used), or two or more Specim IQ capture folders
        (times from each raw header's ``tint``).
    verify
        Scene folders: ``"sha256"`` re-hashes the files listed in
        ``scene.json`` (catches a truncated or altered capture), ``"size"``
        only checks they exist and are non-empty, ``"none"`` skips this. The
        files are hashed by background threads while the cubes are opened.
    bit_depth
        Override the ADC bit depth (default: ``scene.json`` device sensor, else
        12 for 12-bit-range uint16 data).
    allow_partial
        Scene folders: use the complete exposures of a bracket whose capture
        did not finish (an exposure marked ``incomplete``, or planned and never
        started). Without it such a scene is refused, naming the exposure.
    defer_verify
        ``verify="sha256"``: return while one background thread still hashes
        the files; :meth:`Bracket.check_files` (which
        :func:`~mehs.synthesis.fuse.fuse_bracket` calls before it returns)
        waits for it and raises for a file that failed. ``mehs fuse`` fuses
        meanwhile and writes nothing unless the check passed.

    Raises
    ------
    InputError / FormatError
        Naming the folder: fewer than 2 exposures, times not positive or not
        distinct, shapes or wavelengths that differ, a file that fails verification.
    """
    from mehs.io.plausibility import ByteOrderWarning
    from mehs.threadwarn import local_filter

    # a mislabelled byte order would be fused into a plausible-looking wrong cube
    with local_filter("error", ByteOrderWarning):   # this thread only (threaded builds)
        try:
            return _load_bracket(path_or_paths, verify=verify, bit_depth=bit_depth,
                                 allow_partial=allow_partial, defer_verify=defer_verify)
        except ByteOrderWarning as w:
            raise FormatError(f"{w}; refusing to fuse it") from None


def _load_bracket(path_or_paths, *, verify: str, bit_depth: int | None,
                  allow_partial: bool, defer_verify: bool = False) -> Bracket:
    from mehs.io.specim import read_specim_folder

    if isinstance(path_or_paths, (str, Path)):
        paths = [Path(path_or_paths)]
    else:
        paths = [Path(p) for p in path_or_paths]
    if not paths:
        raise InputError("no bracket given")
    if len(paths) == 1 and (paths[0] / "scene.json").is_file():
        return _load_scene(paths[0], verify=verify, bit_depth=bit_depth,
                           allow_partial=allow_partial, defer_verify=defer_verify)
    if len(paths) == 1:
        if not paths[0].exists():
            raise InputError("does not exist", paths[0])
        raise InputError("not a scene folder (no scene.json); give two or more Specim IQ "
                         "folders for a bracket", paths[0])
    caps = [read_specim_folder(p, preview=False) for p in paths]
    times = []
    for p, c in zip(paths, caps):
        if c.raw.integration_time_ms is None:
            raise FormatError("raw cube has no integration time (tint)", p)
        times.append(c.raw.integration_time_ms)
    meta = {"captures": [str(p) for p in paths],
            "metadata": [c.metadata for c in caps]}
    bd = bit_depth or _guess_bit_depth(caps[0].raw, caps[0].metadata)
    darks = [_dark_line(c, p) for p, c in zip(paths, caps)]
    whites = [_white_line(c, t, d, (1 << int(bd)) - 1, p)
              for p, c, t, d in zip(paths, caps, times, darks)]
    return Bracket([c.raw for c in caps], darks, whites, np.asarray(times), caps[0].raw.wavelengths,
                   bit_depth=bd, source=paths[0], metadata=meta)


def unfinished_exposures(doc: dict[str, Any]) -> list[str]:
    """Exposures of a ``scene.json`` document that its capture plan wanted but did not finish.

    Returns one description per exposure, e.g. ``"2 (242 ms, exposures/2_242ms)"``:
    records marked ``incomplete`` and indices of ``plan.times_ms`` with no record.
    """
    recs = [e for e in doc.get("exposures", []) if isinstance(e, dict)]
    out = [f"{e.get('index')} ({e.get('integration_time_ms')} ms, {e.get('folder')})"
           for e in recs if e.get("status") != "complete"]
    plan = doc.get("plan")
    times = plan.get("times_ms") if isinstance(plan, dict) else None
    if isinstance(times, list):
        seen = {e.get("index") for e in recs}
        out += [f"{k} ({t} ms, not started)" for k, t in enumerate(times) if k not in seen]
    return out


def partial_bracket_error(root: Path, missing: list[str]) -> InputError:
    """The refusal of a partial bracket: which exposure, and the two ways forward."""
    return InputError(
        f"the capture of this scene did not finish: exposure {', '.join(missing)} "
        f"{'is' if len(missing) == 1 else 'are'} incomplete. Finish it with 'mehs capture "
        f"--resume --out {root}' (plus the --stage/--camera or --simulate options it was "
        "captured with), or pass --allow-partial to fuse the complete exposures only", root)


def _load_scene(root: Path, *, verify: str, bit_depth: int | None,
                allow_partial: bool = False, defer_verify: bool = False) -> Bracket:
    import json
    import os

    from mehs.io.filecheck import HashCheck

    sj = root / "scene.json"
    try:
        doc = json.loads(sj.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"unreadable scene.json ({exc})", sj) from None
    if not isinstance(doc, dict) or doc.get("format") != "mehs-scene/1":
        raise FormatError("not a mehs-scene/1 file", sj)
    missing = unfinished_exposures(doc)
    if missing and not allow_partial:
        raise partial_bracket_error(root, missing)
    recs = [e for e in doc.get("exposures", []) if isinstance(e, dict)
            and e.get("status") == "complete"]
    if len(recs) < 2:
        raise InputError(f"only {len(recs)} complete exposure(s) in scene.json; a bracket "
                         "needs at least 2", root)
    if verify not in ("sha256", "size", "none"):
        raise InputError(f"verify must be 'sha256', 'size' or 'none', got {verify!r}")
    to_hash = []
    for e in recs:
        for rel, digest in (e.get("files") or {}).items():
            f = root / rel
            if verify != "none" and (not f.is_file() or f.stat().st_size == 0):
                raise FormatError("file listed in scene.json is missing or empty", f)
            to_hash.append((f, digest))
    check = None
    if verify == "sha256" and to_hash:
        # hashed while the cubes are opened (and, deferred, while they are fused)
        check = HashCheck(to_hash, message="SHA-256 does not match scene.json (file altered "
                          "or truncated)", threads=1 if defer_verify else min(2, os.cpu_count() or 1))
    try:
        bracket = _open_scene(root, doc, recs, bit_depth)
    except Exception:
        if check is not None:
            check.result()      # a file that fails its hash explains the failure best
        raise
    if check is not None:
        if defer_verify:
            bracket.file_check = check
        else:
            check.result()
    return bracket


def _open_scene(root: Path, doc: dict[str, Any], recs: list[dict[str, Any]],
                bit_depth: int | None) -> Bracket:
    from mehs.io.envi import read_envi
    from mehs.io.specim import read_specim_folder

    from mehs.capture.scenefolder import check_exposure_record

    exps, darks, times, caps = [], [], [], []
    for e in recs:
        check_exposure_record(e, root / "scene.json")
        folder = root / str(e.get("folder", ""))
        cap = read_specim_folder(folder, preview=False)
        t = e.get("integration_time_ms") or cap.raw.integration_time_ms
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise FormatError(f"exposure has no usable integration time ({t!r})", folder) from None
        th = cap.raw.integration_time_ms
        if th is not None and not _same_time(th, t):
            # which one is right cannot be told, and the time scales every radiance
            raise FormatError(f"scene.json records {t:g} ms for this exposure, its header "
                              f"'tint' {th:g} ms; correct the wrong one", folder)
        exps.append(cap.raw)
        darks.append(_dark_line(cap, folder))
        caps.append((cap, folder))
        times.append(t)
    truth = None
    if doc.get("truth"):
        tp = root / doc["truth"]
        if tp.is_file():
            truth = read_envi(tp)
    device = doc.get("device") or {}
    sensor = device.get("sensor") or {}
    # a real camera's depth is recorded under device.camera (mehs capture); the guess
    # from the data says 12 for a 16-bit camera whose first exposure stays below 4096
    camera = device.get("camera") if isinstance(device.get("camera"), dict) else {}
    bd = bit_depth or sensor.get("bit_depth") or camera.get("bit_depth") \
        or _guess_bit_depth(exps[0], {})
    whites = [_white_line(c, t, d, (1 << int(bd)) - 1, f)
              for (c, f), t, d in zip(caps, times, darks)]
    return Bracket(exps, darks, whites, np.asarray(times), exps[0].wavelengths,
                   bit_depth=int(bd), source=root, truth=truth, metadata=doc)
