"""Specim IQ capture folders: read one into a :class:`SpecimCapture`, write the same layout.

Layout (design.md §2.1)::

    <folder>/                         often named <id>; ids need not be digits
      <id>.png                        preview, 8-bit RGB (mehs writes it in native
                                      ENVI orientation: rows = lines, columns = samples)
      manifest.xml                    <manifest><file extension="hdr|raw|dat|png|xml"
                                      type="capture|darkref|whiteref|whitedarkref|
                                      reflectance|preview|properties">relative/path</file>…
                                      (Specim's types; "raw"/"metadata" also read)
      metadata/<id>.xml               <properties><header><key field="NAME">VALUE</key>…
      capture/<id>.hdr|.raw           raw cube, uint16 (ENVI type 12), bil, byte order 0
      capture/DARKREF_<id>.hdr|.raw   dark reference (usually one line)
      capture/WHITEREF_<id>.hdr|.raw  white reference
      capture/WHITEDARKREF_<id>.*     dark for a pre-set white reference (optional)
      results/REFLECTANCE_<id>.hdr|.dat  float32 bil (optional), with a .png quick-look

Files are located through ``manifest.xml`` when it lists them, otherwise by
these names. The capture id comes from the manifest's raw entry, else from the
one ``capture/*.hdr`` that is not a reference.

References
----------
- Behmann, J. et al. (2018). Specim IQ: evaluation of a new, miniaturized
  handheld hyperspectral camera and its application for plant phenotyping and
  disease detection. *Sensors* 18(2), 441 (folder layout, header keys).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mehs.cube import SpectralCube
from mehs.errors import FormatError, InputError
from mehs.io.atomic import atomic_path, write_text_atomic
from mehs.io.envi import header_files, read_envi, write_envi

__all__ = ["SpecimCapture", "read_specim_folder", "write_specim_folder", "find_captures",
           "is_specim_folder", "REFERENCE_PREFIXES", "make_preview"]

#: File-name prefixes of the reference cubes inside ``capture/``.
REFERENCE_PREFIXES = {"darkref": "DARKREF_", "whiteref": "WHITEREF_",
                      "whitedarkref": "WHITEDARKREF_"}
_REF_PREFIX_RE = re.compile(r"^(DARKREF|WHITEREF|WHITEDARKREF)_", re.IGNORECASE)
_ID_RE = re.compile(r"^[^/\\\s<>:\"|?*]+$")

#: nm of the Specim IQ default bands {70, 53, 19} — used when a cube has none.
_PREVIEW_NM = (598.6, 548.6, 449.4)


@dataclass
class SpecimCapture:
    """One Specim IQ capture: raw cube, references, results and metadata.

    Attributes
    ----------
    capture_id
        The capture's id (file stem in ``capture/``), e.g. ``"444"``.
    root
        The capture folder, or ``None`` for an unsaved capture.
    raw
        Raw cube ``(lines, samples, bands)`` in DN (uint16 on disk),
        ``integration_time_ms`` from the header's ``tint``.
    darkref, whiteref, whitedarkref
        Reference cubes ``(n_lines, samples, bands)`` (usually one line), or ``None``.
    reflectance
        ``results/REFLECTANCE_<id>`` (float32), or ``None``.
    metadata
        ``metadata/<id>.xml`` keys → text values.
    preview
        ``<id>.png`` as uint8 ``(H, W, 3)`` RGB, or ``None``.
    """

    capture_id: str
    root: Path | None
    raw: SpectralCube
    darkref: SpectralCube | None = None
    whiteref: SpectralCube | None = None
    whitedarkref: SpectralCube | None = None
    reflectance: SpectralCube | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    preview: np.ndarray | None = None

    def references(self) -> dict[str, SpectralCube]:
        """The reference cubes present, by kind (``darkref``, ``whiteref``, …)."""
        return {k: getattr(self, k) for k in REFERENCE_PREFIXES if getattr(self, k) is not None}


# --------------------------------------------------------------------- reading


#: manifest ``type`` values → mehs kinds. Specim software types the raw cube
#: "capture" and the metadata XML "properties" (HyperFusion
#: examples/gras_ia10/manifest.xml); mehs wrote "raw"/"metadata" before.
_MANIFEST_TYPES = {"capture": "raw", "raw": "raw", "darkref": "darkref",
                   "whiteref": "whiteref", "whitedarkref": "whitedarkref",
                   "reflectance": "reflectance", "properties": "metadata",
                   "metadata": "metadata", "preview": "preview"}


def _read_manifest(root: Path) -> list[tuple[str, str, str]]:
    """``(kind, extension, relative path)`` entries of ``manifest.xml`` (empty if absent).

    ``kind`` is the manifest ``type`` mapped through :data:`_MANIFEST_TYPES`
    (unknown types are kept lower-cased).
    """
    mf = root / "manifest.xml"
    if not mf.is_file():
        return []
    try:
        tree = ET.parse(mf)
    except ET.ParseError as exc:
        raise FormatError(f"manifest is not valid XML ({exc})", mf) from None
    out = []
    for el in tree.getroot().iter("file"):
        rel = (el.text or "").strip()
        if rel:
            typ = (el.get("type") or "").strip().lower()
            out.append((_MANIFEST_TYPES.get(typ, typ),
                        (el.get("extension") or "").strip().lower(), rel))
    return out


def _read_metadata_xml(path: Path) -> dict[str, str]:
    try:
        tree = ET.parse(path)
    except ET.ParseError as exc:
        raise FormatError(f"metadata is not valid XML ({exc})", path) from None
    return {el.get("field"): (el.text or "").strip()
            for el in tree.getroot().iter("key") if el.get("field")}


#: metadata keys of the integration time: "integration time" (Specim Lumo, HyperFusion
#: gras_ia10.xml), "integration_time" (mehs), any case, "_"/"-"/blank-separated, with an
#: optional unit suffix ("Integration Time (ms)", "integration_time_us")
_TIME_KEY_RE = re.compile(r"^(?:integration[\s_-]*time|tint)(?:[\s_-]*[(\[]?\s*(ms|us|µs|s)\s*[)\]]?)?$",
                          re.IGNORECASE)
_TIME_VALUE_RE = re.compile(r"^\s*(\d+(?:[.,]\d*)?|[.,]\d+)(?:[eE]([+-]?\d+))?\s*(ms|us|µs|s)?\s*$",
                            re.IGNORECASE)
_TIME_UNIT_MS = {"ms": 1.0, "us": 1e-3, "µs": 1e-3, "s": 1e3}


def _metadata_time_ms(metadata: dict[str, str]) -> float | None:
    """The integration time (ms) the metadata XML states, or None.

    Only exact lower-case spellings were read before, so "Integration Time" or a value
    written "15 ms" left a capture without a time (and ``load_bracket`` refused it). A
    unit in the key or the value is honoured (µs ÷ 1000); without one, ms (the IQ's unit).
    """
    for key, text in metadata.items():
        km = _TIME_KEY_RE.match(str(key).strip())
        vm = _TIME_VALUE_RE.match(text or "") if km else None
        if vm is None:
            continue
        value = float(vm.group(1).replace(",", ".")) * 10.0 ** int(vm.group(2) or 0)
        unit = (vm.group(3) or km.group(1) or "ms").lower()
        t = value * _TIME_UNIT_MS[unit]
        if np.isfinite(t) and t > 0:
            return t
    return None


def _existing(path: Path) -> Path:
    """``path``, or the one file in its folder whose name differs only in case (else ``path``)."""
    if path.is_file() or not path.parent.is_dir():
        return path
    want = path.name.lower()
    hits = [p for p in path.parent.iterdir() if p.name.lower() == want and p.is_file()]
    return hits[0] if len(hits) == 1 else path


def _capture_id(root: Path, manifest: list[tuple[str, str, str]]) -> str:
    for typ, ext, rel in manifest:
        if typ == "raw" and rel.lower().endswith(".hdr"):
            return Path(rel).stem
    for typ, ext, rel in manifest:
        if typ == "raw":
            return Path(rel).stem
    stems = sorted({p.stem for p in header_files(root / "capture")
                    if not _REF_PREFIX_RE.match(p.name)})
    if len(stems) == 1:
        return stems[0]
    if root.name in stems:
        return root.name
    if not stems:
        raise FormatError("not a Specim IQ capture: no raw cube capture/<id>.hdr "
                          "(and no manifest.xml naming one)", root)
    raise FormatError(f"several raw cubes in capture/ ({', '.join(stems)}); "
                      "cannot tell which is the capture", root)


def _locate(root: Path, manifest, kind: str, default: str) -> Path:
    """Path of the ``kind`` header: the manifest's entry if it exists, else the conventional name.

    Real manifests list files that are not in the folder (HyperFusion
    gras_ia10 lists a preview PNG it does not ship), so an entry that is
    missing on disk does not hide a conventionally named file.
    """
    for typ, ext, rel in manifest:
        if typ == kind and rel.lower().endswith(".hdr"):
            p = _inside(root, rel)
            if p.is_file():
                return p
    return _existing(root / default)


def _inside(root: Path, rel: str) -> Path:
    """``root / rel``, refusing manifest paths that leave the capture folder."""
    p = root / rel
    if Path(rel).is_absolute() or ".." in Path(rel).parts:
        raise FormatError(f"manifest path {rel!r} points outside the capture folder",
                          root / "manifest.xml")
    return p


def is_specim_folder(path: str | Path) -> bool:
    """Whether ``path`` looks like a Specim IQ capture folder (manifest or capture/<id>.hdr)."""
    p = Path(path)
    if not p.is_dir():
        return False
    if (p / "manifest.xml").is_file():
        return True
    return any(not _REF_PREFIX_RE.match(h.name) for h in header_files(p / "capture"))


def read_specim_folder(path: str | Path, *, require_dark: bool = True,
                       memmap: bool = True, preview: bool = True) -> SpecimCapture:
    """Read a Specim IQ capture folder.

    Parameters
    ----------
    path
        The capture folder.
    require_dark
        If true (default) a missing dark reference is an error; pass false to
        read captures without one (``darkref`` is then ``None``).
    memmap
        Passed to :func:`~mehs.io.envi.read_envi` for every cube.
    preview
        Decode the preview PNG (``preview`` is None without it: a reader of the
        cubes only, such as :func:`~mehs.synthesis.bracket.load_bracket`, skips
        the decoding and OpenCV's import).

    Raises
    ------
    InputError
        The folder does not exist.
    FormatError
        No raw cube, no dark reference (when required), references whose
        samples/bands/wavelengths differ from the raw cube, broken XML, or any
        ENVI problem of the cubes (naming the file).
    """
    root = Path(path)
    if not root.exists():
        raise InputError("folder does not exist", root)
    if not root.is_dir():
        raise InputError("is a file, not a Specim IQ capture folder", root)
    manifest = _read_manifest(root)
    cid = _capture_id(root, manifest)
    raw_hdr = _locate(root, manifest, "raw", f"capture/{cid}.hdr")
    if not raw_hdr.is_file():
        raise FormatError(f"raw cube missing: {raw_hdr.relative_to(root)} not found", root)
    raw = read_envi(raw_hdr, memmap=memmap)

    meta_path = None
    for typ, ext, rel in manifest:
        if typ == "metadata" and rel.lower().endswith(".xml"):  # not the .xsl
            meta_path = _inside(root, rel)
    if meta_path is None or not meta_path.is_file():
        meta_path = _existing(root / "metadata" / f"{cid}.xml")
    metadata = _read_metadata_xml(meta_path) if meta_path.is_file() else {}
    if raw.integration_time_ms is None:
        raw.integration_time_ms = _metadata_time_ms(metadata)

    refs: dict[str, SpectralCube | None] = {}
    for kind, prefix in REFERENCE_PREFIXES.items():
        hdr = _locate(root, manifest, kind, f"capture/{prefix}{cid}.hdr")
        if not hdr.is_file():
            refs[kind] = None
            if kind == "darkref" and require_dark:
                raise FormatError(
                    f"dark reference missing: {hdr.relative_to(root)} not found "
                    "(read with require_dark=False to continue without)", root)
            continue
        ref = read_envi(hdr, memmap=memmap)
        _check_matches(raw, ref, hdr)
        refs[kind] = ref

    refl_hdr = _locate(root, manifest, "reflectance", f"results/REFLECTANCE_{cid}.hdr")
    reflectance = None
    if refl_hdr.is_file():
        reflectance = read_envi(refl_hdr, memmap=memmap)
        if reflectance.units in ("unknown", "DN"):
            reflectance.units = "reflectance"

    image = None
    prev_path = None
    for typ, ext, rel in manifest:
        if typ == "preview":
            prev_path = _inside(root, rel)
    if prev_path is None or not prev_path.is_file():
        prev_path = _existing(root / f"{cid}.png")
    if preview and prev_path.is_file():
        image = _read_png(prev_path)
    return SpecimCapture(cid, root, raw, refs["darkref"], refs["whiteref"],
                         refs["whitedarkref"], reflectance, metadata, image)


def _check_matches(raw: SpectralCube, ref: SpectralCube, path: Path) -> None:
    if ref.samples != raw.samples or ref.bands != raw.bands:
        raise FormatError(f"reference has {ref.samples} samples × {ref.bands} bands, "
                          f"the raw cube {raw.samples} × {raw.bands}", path)
    if not np.allclose(ref.wavelengths, raw.wavelengths, rtol=0, atol=1e-3):
        raise FormatError("reference wavelengths differ from the raw cube's", path)


def _read_png(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise FormatError("preview image cannot be decoded", path)
    return np.ascontiguousarray(img[:, :, ::-1])


# --------------------------------------------------------------------- writing


def make_preview(cube: SpectralCube) -> np.ndarray:
    """uint8 ``(lines, samples, 3)`` RGB quick-look from the cube's default bands.

    Bands: ``cube.default_bands`` or those nearest 598.6/548.6/449.4 nm (the
    Specim IQ defaults). One scale for all three channels (99.5th percentile
    of a subsample, so colours are not re-balanced), then a 1/2.2 gamma.
    """
    bands = cube.default_bands or tuple(cube.band_index(w) for w in _PREVIEW_NM)
    rgb = np.stack([np.asarray(cube.data[:, :, b], dtype=np.float32) for b in bands], axis=-1)
    rgb = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    step = max(1, int(np.sqrt(rgb.shape[0] * rgb.shape[1] / 65536)))
    hi = float(np.percentile(rgb[::step, ::step], 99.5)) if rgb.size else 0.0
    lo = min(0.0, float(rgb.min())) if rgb.size else 0.0
    scale = (hi - lo) if hi > lo else 1.0
    x = np.clip((rgb - lo) / scale, 0.0, 1.0) ** (1 / 2.2)
    return (x * 255.0 + 0.5).astype(np.uint8)


def _write_png(path: Path, rgb: np.ndarray, overwrite: bool) -> None:
    import cv2

    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"preview must be uint8 (H, W, 3), got {img.dtype} {img.shape}", path)
    with atomic_path(path, overwrite=overwrite) as tmp:
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(img[:, :, ::-1]))
        if not ok:  # pragma: no cover - cv2 failure
            raise FormatError("PNG encoding failed", path)
        tmp.write_bytes(buf.tobytes())


def _xml_text(root: ET.Element) -> str:
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_specim_folder(path: str | Path, capture: SpecimCapture, *,
                        overwrite: bool = False) -> Path:
    """Write ``capture`` as a Specim IQ folder at ``path``; return the folder.

    A new folder is assembled under a hidden temporary name beside ``path`` and
    renamed into place when complete, so an existing ``path`` always holds a
    whole capture. Raw, reference cubes are written as uint16 bil ``.raw``
    (values must fit 0..65535), the reflectance as float32 bil ``.dat``; a
    preview is made from the raw cube's default bands when ``capture.preview``
    is ``None``.

    Parameters
    ----------
    overwrite
        If false (default), refuse (InputError) when ``path`` exists and is not
        empty — raw captures are never overwritten. If true, files of the same
        names are replaced one by one (each atomically), and the old capture's
        references and reflectance that the new one lacks are removed.
    """
    dest = Path(path)
    cid = str(capture.capture_id)
    if not cid or not _ID_RE.match(cid) or cid in (".", ".."):
        raise InputError(f"invalid capture id {cid!r} (no slashes, spaces or "
                         "reserved characters)", dest)
    if dest.exists() and not dest.is_dir():
        raise InputError("exists and is not a folder", dest)
    exists = dest.is_dir() and any(dest.iterdir())
    if exists and not overwrite:
        raise InputError("refusing to overwrite an existing capture folder", dest)
    if exists:
        _write_contents(dest, capture, cid, overwrite=True)
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.part-", dir=dest.parent))
    try:
        # mkdtemp makes it 0700; a capture folder gets the mode any new folder would get
        umask = os.umask(0)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)
        _write_contents(tmp, capture, cid, overwrite=False)
        if dest.is_dir():
            dest.rmdir()  # empty (checked above); os.replace needs it gone
        os.replace(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return dest


def _write_contents(root: Path, cap: SpecimCapture, cid: str, *, overwrite: bool) -> None:
    entries: list[tuple[str, str, str]] = []

    def cube(kind: str, rel_stem: str, c: SpectralCube, dtype, ext: str) -> None:
        write_envi(root / f"{rel_stem}.hdr", c, dtype=dtype, interleave="bil",
                   data_ext=ext, overwrite=overwrite)
        entries.append((kind, "hdr", f"{rel_stem}.hdr"))
        entries.append((kind, ext.lstrip("."), f"{rel_stem}{ext}"))

    if not isinstance(cap.raw, SpectralCube):
        raise InputError("a capture needs a raw SpectralCube", root)
    cube("raw", f"capture/{cid}", cap.raw, np.uint16, ".raw")
    if overwrite:
        # a reference or result the new capture lacks must not survive from the old one:
        # the reader finds them by their standard names, manifest or not
        stale = [f"capture/{prefix}{cid}" for kind, prefix in REFERENCE_PREFIXES.items()
                 if getattr(cap, kind) is None]
        if cap.reflectance is None:
            stale.append(f"results/REFLECTANCE_{cid}")
        for rel in stale:
            for ext in (".hdr", ".raw", ".dat", ".png"):      # the header first
                (root / f"{rel}{ext}").unlink(missing_ok=True)
    for kind, prefix in REFERENCE_PREFIXES.items():
        ref = getattr(cap, kind)
        if ref is not None:
            _check_matches(cap.raw, ref, root / f"capture/{prefix}{cid}.hdr")
            cube(kind, f"capture/{prefix}{cid}", ref, np.uint16, ".raw")
    if cap.reflectance is not None:
        cube("reflectance", f"results/REFLECTANCE_{cid}", cap.reflectance, np.float32, ".dat")
        # the IQ writes a quick-look beside its reflectance result (iqcampy demo
        # folder: results/REFLECTANCE_<id>.png); RGBSCENE_/RGBVIEWFINDER_/
        # RGBBACKGROUND_ come from the IQ's separate RGB camera, so mehs has none
        _write_png(root / f"results/REFLECTANCE_{cid}.png", make_preview(cap.reflectance),
                   overwrite)
        entries.append(("reflectance", "png", f"results/REFLECTANCE_{cid}.png"))

    # Specim nests the keys in <header> (HyperFusion examples/gras_ia10/metadata)
    props = ET.Element("properties")
    section = ET.SubElement(props, "header")
    for k, v in (cap.metadata or {}).items():
        el = ET.SubElement(section, "key", field=str(k))
        el.text = str(v)
    write_text_atomic(root / "metadata" / f"{cid}.xml", _xml_text(props), overwrite=overwrite)
    entries.append(("properties", "xml", f"metadata/{cid}.xml"))

    preview = cap.preview if cap.preview is not None else make_preview(cap.raw)
    _write_png(root / f"{cid}.png", preview, overwrite)
    entries.append(("preview", "png", f"{cid}.png"))

    man = ET.Element("manifest")
    for typ, ext, rel in entries:
        # Specim's own layout: raw cube typed "capture", attributes extension, type
        el = ET.SubElement(man, "file", extension=ext,
                           type="capture" if typ == "raw" else typ)
        el.text = rel
    # the manifest is written last: its presence marks a complete folder
    write_text_atomic(root / "manifest.xml", _xml_text(man), overwrite=overwrite)


# --------------------------------------------------------------------- finding


def find_captures(root: str | Path) -> list[Path]:
    """All Specim IQ capture folders under ``root`` (itself included), sorted by path.

    A capture folder has ``manifest.xml`` or a raw ``capture/<id>.hdr``; the
    search does not descend into captures, nor into hidden folders (e.g.
    unfinished ``.name.part-*`` writes).
    """
    base = Path(root)
    if not base.exists():
        raise InputError("folder does not exist", base)
    if not base.is_dir():
        raise InputError("is a file, not a folder", base)
    found = []
    for dirpath, dirnames, _files in os.walk(base):
        d = Path(dirpath)
        if is_specim_folder(d):
            found.append(d)
            dirnames[:] = []
            continue
        dirnames[:] = sorted(n for n in dirnames if not n.startswith("."))
    return sorted(found, key=lambda p: str(p))

