"""Real-world ENVI headers and Specim capture folders, reproduced as small fixtures.

Each fixture keeps the header text / XML layout of a file found in a public
repository or issue thread (named in a comment beside it); only ``samples``,
``lines``, ``bands`` and the per-band lists are cut down so the synthesised
data stay tiny. Numbers are deterministic (``np.arange``) so a wrong byte
order, interleave or offset shows up as wrong values.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mehs.errors import FormatError
from mehs.io import load_cube, read_envi

# Specim FX10e (Lumo - Scanner) wavelengths and FWHM, first six bands, as written
# (two decimals, one per line, comma at the line end, "}" on its own line).
_LUMO_WL = ["397.01", "398.32", "399.63", "400.93", "402.24", "403.55"]
_LUMO_FWHM = ["1.31"] * 6


def lumo_header(samples: int, lines: int, *, start="19:03:45", stop="19:04:03",
                nl: str = "\n") -> str:
    """Header of a Specim Lumo capture, key for key.

    Source: jy773Cornell/HyperFusion, examples/gras_ia10/capture/gras_ia10.hdr and
    DARKREF_gras_ia10.hdr (1024 samples × 448 bands there; here 6 bands).
    Its CR LF variant: the same writer's ``\\r\\n`` output in the specsensor_cli
    code found by the same search (``out << "ENVI\\r\\n"``).
    """
    text = f"""ENVI
description = {{
File Imported into ENVI}}
file type = ENVI

sensor type = FX10e , Lumo - Scanner v2020-586
acquisition date = DATE(yyyy-mm-dd): 2025-10-31
Start Time = UTC TIME: {start}
Stop Time = UTC TIME: {stop}

samples = {samples}
bands = 6
lines = {lines}

errors = {{none}}

interleave = bil
data type = 12
header offset = 0
byte order = 0
x start = 0
y start = 0
default bands = {{6, 4, 1}}

himg = {{1, {samples}}}
vimg = {{1, 6}}
hroi = {{1, {samples}}}
vroi = {{1, 6}}

fps = 50.00
fps_qpf = 50.05
tint = 15.000000
binning = {{1, 1}}
trigger mode = Internal
fodis = {{0, 0}}
sensorid = 3210441
acquisitionwindow left = 112
acquisitionwindow top = 285
calibration pack = C:/SPECIM/fx10e_these_calpacks/3210441_20211027_FX_calpack.scp

VNIR temperature = 48.43

temperature = {{
48.43
}}


Wavelength = {{
{(","+chr(10)).join(_LUMO_WL)}
}}

fwhm = {{
{(","+chr(10)).join(_LUMO_FWHM)}
}}
"""
    return text.replace("\n", nl)


def write_pair(folder, stem, header, data_lbs, *, ext=".raw", dtype="<u2", prefix=b"",
               header_bytes=None):
    """Header + data file; ``data_lbs`` is given in FILE order (already interleaved)."""
    folder.mkdir(parents=True, exist_ok=True)
    hp = folder / f"{stem}.hdr"
    if header_bytes is not None:
        hp.write_bytes(header_bytes)
    else:
        hp.write_bytes(header.encode("utf-8"))
    (folder / f"{stem}{ext}").write_bytes(prefix + np.asarray(data_lbs).astype(dtype).tobytes())
    return hp


def bil_counts(lines, samples, bands=6, start=0):
    """(lines, samples, bands) uint16 test cube and its BIL file order."""
    cube = (np.arange(lines * samples * bands) + start).reshape(lines, samples, bands)
    return cube.astype(np.uint16), cube.transpose(0, 2, 1)


@pytest.mark.parametrize("nl", ["\n", "\r\n"])
def test_specim_lumo_header_lf_and_crlf(tmp_path, nl):
    cube, fileorder = bil_counts(3, 4)
    hp = write_pair(tmp_path, "gras_ia10", lumo_header(4, 3, nl=nl), fileorder)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing here deserves a warning
        c = read_envi(hp)
    np.testing.assert_array_equal(c.data, cube)
    np.testing.assert_array_equal(c.wavelengths, [float(w) for w in _LUMO_WL])
    np.testing.assert_array_equal(c.fwhm, 1.31)
    assert c.integration_time_ms == 15.0
    assert c.default_bands == (5, 3, 0)
    assert c.binning == (1, 1)
    assert c.metadata["sensor type"] == "FX10e , Lumo - Scanner v2020-586"
    assert c.metadata["description"] == "File Imported into ENVI"
    assert c.metadata["errors"] == ["none"]
    assert c.metadata["temperature"] == ["48.43"]
    assert c.metadata["calibration pack"].endswith("_FX_calpack.scp")


def test_utf8_bom_header(tmp_path):
    # Windows editors (Notepad "UTF-8") prepend EF BB BF; SPy then reports
    # "missing ENVI at beginning of first line".
    cube, fileorder = bil_counts(3, 4)
    text = lumo_header(4, 3, nl="\r\n")
    hp = write_pair(tmp_path, "bom", None, fileorder,
                    header_bytes=b"\xef\xbb\xbf" + text.encode("utf-8"))
    c = read_envi(hp)
    np.testing.assert_array_equal(c.data, cube)
    assert c.integration_time_ms == 15.0


def test_cp1252_description_and_units(tmp_path):
    # a header saved in code page 1252: "µ" is the single byte 0xB5 (not UTF-8)
    data = np.arange(2 * 3 * 2, dtype=np.uint16).reshape(2, 3, 2)
    text = ("ENVI\r\ndescription = {Messung 20 °C, Objektiv 17 µm}\r\nsamples = 2\r\n"
            "lines = 2\r\nbands = 3\r\ndata type = 12\r\ninterleave = bsq\r\n"
            "byte order = 0\r\nwavelength units = µm\r\nwavelength = {0.45, 0.55, 0.65}\r\n")
    hp = write_pair(tmp_path, "cp", None, data, header_bytes=text.encode("cp1252"))
    c = read_envi(hp)
    np.testing.assert_allclose(c.wavelengths, [450, 550, 650])
    assert "µm" in c.metadata["description"]


def test_headwall_leading_comma_wavelengths(tmp_path):
    # Source: tnigon/hs_process issue #2 (Headwall Hyperspec III header):
    # one value per line with the comma at the START of the next line, bsq,
    # "wavelength units = nm", a map info list with "units=Degrees".
    header = """ENVI
description = {HEADWALL Hyperspec III[HEADWALL Hyperspec III],[HEADWALL Hyperspec III OR]}
samples = 3
lines = 2
bands = 4
header offset = 0
file type = ENVI Standard
data type = 12
interleave = bsq
sensor type = Unknown
byte order = 0
wavelength units = nm
map info = {Geographic Lat/Lon,1,1,-89.38681637930115,43.29648597737143,3.080735373867722e-7,2.250256219444636e-7,WGS84,units=Degrees}
wavelength = {
399.309
,401.521
,403.732
,405.944
}
"""
    cube = np.arange(2 * 3 * 4, dtype=np.uint16).reshape(2, 3, 4)
    hp = write_pair(tmp_path, "headwall", header, cube.transpose(2, 0, 1))
    c = read_envi(hp)
    np.testing.assert_array_equal(c.data, cube)
    np.testing.assert_array_equal(c.wavelengths, [399.309, 401.521, 403.732, 405.944])
    assert c.metadata["map info"][-1] == "units=Degrees"


def test_fenix_uint16_reflectance_scale_factor_and_ignore_value(tmp_path):
    # Source: a Specim Fenix reflectance subset quoted in a public diff (ENVI
    # "File Resize Result"): uint16 (type 12) with reflectance scale factor
    # 65535, data ignore value = 0, "lines   =" padded, lists opened on one
    # line and continued on the next with a leading space, two tints.
    header = """ENVI
description = {
  File Resize Result, x resize factor: 1.000000, y resize factor: 1.000000.}
samples = 3
lines   = 2
bands   = 4
header offset = 0
file type = ENVI Standard
data type = 12
interleave = bsq
sensor type = Fenix
byte order = 0
x start = 247
y start = 425
default bands = {4,3,2}
wavelength units = Nanometers
reflectance scale factor = 65535.000000
data ignore value = 0
fwhm = {
 3.360000, 3.360000, 3.360000, 3.370000}
wavelength = {
 400.120000, 403.480000, 406.850000, 410.210000}
binning = {
 4, 2}
tint1 = 18.000000
tint2 = 4.455800
"""
    cube = (np.arange(2 * 3 * 4) * 1000).reshape(2, 3, 4).astype(np.uint16)
    hp = write_pair(tmp_path, "fenix", header, cube.transpose(2, 0, 1))
    c = read_envi(hp)
    assert c.data.dtype == np.float32 and c.units == "reflectance"
    np.testing.assert_allclose(c.data, cube / np.float32(65535), rtol=1e-6)
    assert c.binning == (4, 2) and c.default_bands == (3, 2, 1)
    assert c.integration_time_ms is None  # two sensors, two tints: none is "the" tint
    # the ignore marker is scaled with the data: stored 0 → 0.0 reflectance
    assert c.metadata["data ignore value"] == 0.0


def test_ignore_value_scaled_with_the_data_and_written_back(tmp_path):
    # EnMAP-Box style int16 with 'data ignore value = -9999' plus a reflectance
    # scale factor of 10000 (ENVI's usual integer reflectance encoding)
    from mehs.io import write_envi

    header = """ENVI
samples = 2
lines   = 1
bands   = 3
header offset = 0
file type = ENVI Standard
data type = 2
interleave = bsq
byte order = 0
data ignore value = -9999
reflectance scale factor = 10000
wavelength = {402.1, 500.2, 600.3}
wavelength units = Nanometer
"""
    stored = np.array([[[-9999, 2500, 5000], [1000, -9999, 7500]]], np.int16)
    hp = write_pair(tmp_path, "refl", header, stored.transpose(2, 0, 1), ext=".bsq",
                    dtype="<i2")
    c = read_envi(hp)
    ignore = c.metadata["data ignore value"]
    np.testing.assert_array_equal(c.data == ignore, stored == -9999)
    back = read_envi(write_envi(tmp_path / "out.hdr", c, data_ext=".dat"))
    np.testing.assert_array_equal(back.data == float(back.metadata["data ignore value"]),
                                  stored == -9999)


def test_enmap_box_header_nanometer_and_band_names(tmp_path):
    # Source: EnMAP-Box/enmap-box issue #933 / #741: int16 bsq, "Nanometer"
    # (singular), description on the next line, band names list, data ignore value.
    header = """ENVI
description = {
E:/20220530_AVIRIS_NG_Irlbach/Irlbach/400_2500nm_Cut/ang20210530t101445_rfl_wlCut.bsq}
samples = 3
lines   = 2
bands   = 3
header offset = 0
file type = ENVI Standard
data type = 2
interleave = bsq
byte order = 0
map info = {UTM, 1, 1, 332499.642028, 5419368.76286, 5.3, 5.3, 33, North,WGS-84}
band names = {
Band 1,
Band 2,
Band 3}
data ignore value = -9999
fwhm = {5.590000000000001, 6.0200000000000005, 6.0200000000000005}
wavelength = {402.11182099999996, 2490.731821, 2495.741821}
wavelength units = Nanometer
"""
    cube = (np.arange(2 * 3 * 3) - 5).reshape(2, 3, 3).astype(np.int16)
    hp = write_pair(tmp_path, "enmap", header, cube.transpose(2, 0, 1), ext=".bsq",
                    dtype="<i2")
    c = read_envi(hp)
    np.testing.assert_array_equal(c.data, cube)
    assert c.metadata["band names"] == ["Band 1", "Band 2", "Band 3"]
    np.testing.assert_allclose(c.wavelengths, [402.111821, 2490.731821, 2495.741821])


def test_trailing_comma_in_lists(tmp_path):
    # A comma after the last value ("398.32,\n}") as written by loops that
    # print "value," for every band; it is not a missing last value.
    cube, fileorder = bil_counts(2, 3)
    text = lumo_header(3, 2).replace("403.55\n}", "403.55,\n}")
    hp = write_pair(tmp_path, "trail", text, fileorder)
    c = read_envi(hp)
    np.testing.assert_array_equal(c.wavelengths, [float(w) for w in _LUMO_WL])
    # an empty value in the middle is still an error, naming the band
    bad = lumo_header(3, 2).replace("399.63,\n", ",\n")
    hp = write_pair(tmp_path, "hole", bad, fileorder)
    with pytest.raises(FormatError, match=r"hole\.hdr: 'wavelength'"):
        read_envi(hp)


def test_load_cube_reads_real_header_by_data_file(tmp_path):
    cube, fileorder = bil_counts(3, 4)
    write_pair(tmp_path, "gras_ia10", lumo_header(4, 3, nl="\r\n"), fileorder)
    c = load_cube(tmp_path / "gras_ia10.raw")
    np.testing.assert_array_equal(c.data, cube)


def test_specim_start_time_completes_acquisition_date(tmp_path):
    # Specim writes the day in "acquisition date = DATE(yyyy-mm-dd): …" and the
    # clock in "Start Time = UTC TIME: …" (HyperFusion gras_ia10.hdr above).
    cube, fileorder = bil_counts(3, 4)
    hp = write_pair(tmp_path, "t", lumo_header(4, 3, start="19:03:45"), fileorder)
    c = read_envi(hp)
    assert c.acquisition_date == "2025-10-31T19:03:45+00:00"
    assert c.metadata["start time"] == "UTC TIME: 19:03:45"
    # a start time that is not a time leaves the day alone
    hp = write_pair(tmp_path, "u", lumo_header(4, 3, start="unknown"), fileorder)
    assert read_envi(hp).acquisition_date == "2025-10-31"


# ----------------------------------------------------------------- capture folders

# Source: jy773Cornell/HyperFusion examples/gras_ia10/manifest.xml — a Specim
# folder as the camera software writes it: "extension" before "type", the raw
# cube typed "capture", the metadata "properties", and a preview entry whose
# PNG is not in the folder.
GRAS_MANIFEST = """<?xml version="1.0" encoding="utf-8"?>
<manifest>
 <file extension="raw" type="darkref">capture/DARKREF_gras_ia10.raw</file>
 <file extension="hdr" type="darkref">capture/DARKREF_gras_ia10.hdr</file>
 <file extension="raw" type="whiteref">capture/WHITEREF_gras_ia10.raw</file>
 <file extension="hdr" type="whiteref">capture/WHITEREF_gras_ia10.hdr</file>
 <file extension="raw" type="capture">capture/gras_ia10.raw</file>
 <file extension="hdr" type="capture">capture/gras_ia10.hdr</file>
 <file extension="xml" type="properties">metadata/gras_ia10.xml</file>
 <file extension="xsl" type="properties">metadata/gras_ia10.xsl</file>
 <file extension="png" type="preview">gras_ia10.png</file>
</manifest>
"""

# Source: the same folder, metadata/gras_ia10.xml: a stylesheet processing
# instruction and the keys nested in <header> and <userdefined> sections.
GRAS_METADATA = """<?xml version="1.0" encoding="UTF-8" standalone="yes"?>
<?xml-stylesheet type="text/xsl" href="gras_ia10.xsl"?>
<properties><header><key field="sensor type">FX10e</key>
        <key field="sensor id">3210441</key>
        <key field="frame rate">50</key>
        <key field="integration time">15</key>
        <key field="samples">1024</key>
        <key field="active bands">448</key>
        <key field="spatial binning">1</key>
        <key field="spectral binning">1</key>
        <key field="frames recorded">921</key>
        <key field="frames dropped">0</key>
        <key field="data format">BIL</key>
        <key field="date">2025-10-31</key>
        <key field="date text">Friday, October 31, 2025</key>
        <key field="time">19:03:35</key>
        <key field="calibration pack">C:/SPECIM/fx10e_these_calpacks/3210441_20211027_FX_calpack.scp</key>
    </header>
    <userdefined><key field="sample name">gras_ia10</key>
        <key field="operator">jy</key>
        <key field="description"></key>
        <key field="sensor temperature">48.395446777344</key>
        <key field="sensor prefix"></key>
    </userdefined>
</properties>
"""


def make_gras_folder(root, *, samples=4, lines=3, dark_lines=2, crlf=False, tint=True):
    """The gras_ia10 Specim folder with tiny cubes (100-line dark reference → 2)."""
    nl = "\r\n" if crlf else "\n"
    folder = root / "gras_ia10"
    cap = folder / "capture"
    raw, raw_f = bil_counts(lines, samples, start=100)
    dark, dark_f = bil_counts(dark_lines, samples, start=0)
    white, white_f = bil_counts(1, samples, start=3000)
    hdr = lumo_header(samples, lines, nl=nl)
    if not tint:
        hdr = hdr.replace("tint = 15.000000" + nl, "")
    write_pair(cap, "gras_ia10", hdr, raw_f)
    write_pair(cap, "DARKREF_gras_ia10",
               lumo_header(samples, dark_lines, start="19:03:36", stop="19:03:38", nl=nl),
               dark_f)
    write_pair(cap, "WHITEREF_gras_ia10", lumo_header(samples, 1, nl=nl), white_f)
    (folder / "metadata").mkdir()
    (folder / "manifest.xml").write_text(GRAS_MANIFEST)
    (folder / "metadata" / "gras_ia10.xml").write_text(GRAS_METADATA)
    (folder / "metadata" / "gras_ia10.xsl").write_text(
        '<?xml version="1.0"?><xsl:stylesheet version="1.0" '
        'xmlns:xsl="http://www.w3.org/1999/XSL/Transform"/>\n')
    (folder / "properties.xml").write_text(
        '<?xml version="1.0" encoding="UTF-8"?>\n<properties>'
        '<property name="countervalue">0000</property></properties>\n')
    (cap / "gras_ia10.log").write_text("  0 dropped frame incidents, 0 dropped frames\n")
    return folder, raw, dark, white


def test_real_specim_folder_reads(tmp_path):
    from mehs.io import find_captures, read_specim_folder

    folder, raw, dark, white = make_gras_folder(tmp_path, crlf=True)
    cap = read_specim_folder(folder)
    assert cap.capture_id == "gras_ia10"
    np.testing.assert_array_equal(cap.raw.data, raw)
    np.testing.assert_array_equal(cap.darkref.data, dark)
    np.testing.assert_array_equal(cap.whiteref.data, white)
    assert cap.darkref.lines == 2  # a multi-line dark, not a one-line slab
    assert cap.preview is None  # listed in the manifest, absent on disk
    assert cap.metadata["integration time"] == "15"
    assert cap.metadata["operator"] == "jy"  # <userdefined> keys are read too
    assert cap.raw.acquisition_date == "2025-10-31T19:03:45+00:00"
    assert find_captures(tmp_path) == [folder]
    np.testing.assert_array_equal(load_cube(folder).data, raw)


def test_real_folder_integration_time_from_metadata_key(tmp_path):
    # without "tint" in the header the time comes from <key field="integration time">
    from mehs.io import read_specim_folder

    folder, *_ = make_gras_folder(tmp_path, tint=False)
    assert read_specim_folder(folder).raw.integration_time_ms == 15.0


def test_real_manifest_capture_type_names_the_raw_cube(tmp_path):
    # a second cube in capture/ (an export beside the camera's own) — the
    # manifest's type="capture" entry says which is the capture
    from mehs.io import read_specim_folder

    folder, raw, *_ = make_gras_folder(tmp_path)
    # folders get renamed by users ("plant <N>" folders of a published IQ data set)
    folder = folder.rename(tmp_path / "plant 1")
    cap = folder / "capture"
    (cap / "gras_ia10_subset.hdr").write_bytes((cap / "gras_ia10.hdr").read_bytes())
    (cap / "gras_ia10_subset.raw").write_bytes(b"\0" * (cap / "gras_ia10.raw").stat().st_size)
    got = read_specim_folder(folder)
    assert got.capture_id == "gras_ia10"
    np.testing.assert_array_equal(got.raw.data, raw)


def test_manifest_entry_missing_on_disk_falls_back_to_names(tmp_path):
    from mehs.io import read_specim_folder

    folder, raw, *_ = make_gras_folder(tmp_path)
    mf = folder / "manifest.xml"
    mf.write_text(mf.read_text().replace("capture/WHITEREF_gras_ia10.hdr",
                                         "capture/WHITEREF_old_name.hdr"))
    assert read_specim_folder(folder).whiteref is not None


def test_written_folder_follows_the_real_layout(tmp_path):
    # what write_specim_folder writes is laid out like GRAS_MANIFEST/GRAS_METADATA
    import xml.etree.ElementTree as ET

    import spectral.io.envi as spy_envi

    from mehs.io import read_specim_folder, write_specim_folder

    folder, raw, dark, white = make_gras_folder(tmp_path / "in")
    cap = read_specim_folder(folder)
    out = write_specim_folder(tmp_path / "out" / "gras_ia10", cap)
    files = ET.parse(out / "manifest.xml").getroot()
    assert files.tag == "manifest"
    got = {(f.get("type"), f.get("extension"), f.text) for f in files.iter("file")}
    real = {(f.get("type"), f.get("extension"), f.text)
            for f in ET.fromstring(GRAS_MANIFEST).iter("file")}
    # every cube, metadata and preview entry is typed and named as Specim does
    assert real - got == {("properties", "xsl", "metadata/gras_ia10.xsl")}
    assert list(files.iter("file"))[0].keys() == ["extension", "type"]
    meta = ET.parse(out / "metadata" / "gras_ia10.xml").getroot()
    assert meta.tag == "properties" and meta[0].tag == "header"
    assert meta[0].find("key[@field='integration time']").text == "15"
    back = read_specim_folder(out)
    np.testing.assert_array_equal(back.raw.data, raw)
    np.testing.assert_array_equal(back.darkref.data, dark)
    assert back.metadata == cap.metadata
    img = spy_envi.open(str(out / "capture" / "gras_ia10.hdr"))
    np.testing.assert_array_equal(img.open_memmap(), raw)
    assert float(img.metadata["tint"]) == 15.0


def test_folders_written_by_older_mehs_still_read(tmp_path):
    # before following Specim, mehs typed the raw cube "raw" and metadata "metadata"
    from mehs.io import read_specim_folder

    folder, raw, *_ = make_gras_folder(tmp_path)
    mf = folder / "manifest.xml"
    mf.write_text(mf.read_text().replace('type="capture"', 'type="raw"')
                  .replace('type="properties"', 'type="metadata"'))
    got = read_specim_folder(folder.rename(tmp_path / "renamed"))
    assert got.capture_id == "gras_ia10" and got.metadata["operator"] == "jy"


def test_mehs_info_on_real_folder_and_header(tmp_path, capsys):
    import json

    from mehs.cli import main

    folder, raw, *_ = make_gras_folder(tmp_path, crlf=True)
    assert main(["info", str(folder), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["capture_id"] == "gras_ia10" and info["manifest"] is True
    assert info["references"]["darkref"]["shape"] == [2, 4, 6]
    assert info["missing"] == []
    assert info["raw"]["values"]["max"] == int(raw.max())
    # a header with a byte-order mark, given by its data file
    text = lumo_header(4, 3, nl="\r\n")
    _, fileorder = bil_counts(3, 4)
    write_pair(tmp_path, "bom", None, fileorder,
               header_bytes=b"\xef\xbb\xbf" + text.encode("utf-8"))
    assert main(["info", str(tmp_path / "bom.raw")]) == 0
    assert "15" in capsys.readouterr().out


# Source: fligt/iqcampy notebooks/10_reading-iqcam-data.ipynb — the header of a
# real Specim IQ capture (demo data set iqcam_2021-02-03_005) as printed there,
# and its 204 band centres (nm, two decimals as printed). The wavelength list
# itself is not printed there; iqcampy parses it as lower-case
# "wavelength = {…}" at the end of the header, values comma-separated across
# lines, which is how it is written here.
IQ_WAVELENGTHS = [
    397.32, 400.2, 403.09, 405.97, 408.85, 411.74, 414.63, 417.52, 420.4, 423.29, 426.19,
    429.08, 431.97, 434.87, 437.76, 440.66, 443.56, 446.45, 449.35, 452.25, 455.16, 458.06,
    460.96, 463.87, 466.77, 469.68, 472.59, 475.5, 478.41, 481.32, 484.23, 487.14, 490.06,
    492.97, 495.89, 498.8, 501.72, 504.64, 507.56, 510.48, 513.4, 516.33, 519.25, 522.18,
    525.1, 528.03, 530.96, 533.89, 536.82, 539.75, 542.68, 545.62, 548.55, 551.49, 554.43,
    557.36, 560.3, 563.24, 566.18, 569.12, 572.07, 575.01, 577.96, 580.9, 583.85, 586.8,
    589.75, 592.7, 595.65, 598.6, 601.55, 604.51, 607.46, 610.42, 613.38, 616.34, 619.3,
    622.26, 625.22, 628.18, 631.15, 634.11, 637.08, 640.04, 643.01, 645.98, 648.95, 651.92,
    654.89, 657.87, 660.84, 663.81, 666.79, 669.77, 672.75, 675.73, 678.71, 681.69, 684.67,
    687.65, 690.64, 693.62, 696.61, 699.6, 702.58, 705.57, 708.57, 711.56, 714.55, 717.54,
    720.54, 723.53, 726.53, 729.53, 732.53, 735.53, 738.53, 741.53, 744.53, 747.54, 750.54,
    753.55, 756.56, 759.56, 762.57, 765.58, 768.6, 771.61, 774.62, 777.64, 780.65, 783.67,
    786.68, 789.7, 792.72, 795.74, 798.77, 801.79, 804.81, 807.84, 810.86, 813.89, 816.92,
    819.95, 822.98, 826.01, 829.04, 832.07, 835.11, 838.14, 841.18, 844.22, 847.25, 850.29,
    853.33, 856.37, 859.42, 862.46, 865.5, 868.55, 871.6, 874.64, 877.69, 880.74, 883.79,
    886.84, 889.9, 892.95, 896.01, 899.06, 902.12, 905.18, 908.24, 911.3, 914.36, 917.42,
    920.48, 923.55, 926.61, 929.68, 932.74, 935.81, 938.88, 941.95, 945.02, 948.1, 951.17,
    954.24, 957.32, 960.4, 963.47, 966.55, 969.63, 972.71, 975.79, 978.88, 981.96, 985.05,
    988.13, 991.22, 994.31, 997.4, 1000.49, 1003.58]


def iq_header(samples: int, lines: int, *, data_type: int = 12) -> str:
    """The Specim IQ header (512 × 512 there; here ``samples`` × ``lines``)."""
    wl = ",\n".join(f"{w:.2f}" for w in IQ_WAVELENGTHS)
    return f"""ENVI
description = {{Data recorded with Specim IQ}}
samples = {samples}
lines = {lines}
bands = 204
header offset = 0
file type = ENVI
data type = {data_type}
interleave = BIL
sensor type = SPECIM IQ
byte order = 0
default bands = {{70,53,19}}
latitude = 0.00000000
longitude = 0.00000000
acquisition date = 03-02-2021
errors = none
binning = {{1,1}}
tint = 98
fps = 10.2041
wavelength = {{
{wl}
}}
"""


def make_iq_folder(root, *, samples=3, lines=2):
    """The iqcampy demo folder's tree (fligt/iqcampy, same notebook): the folder
    is named differently from the capture id, has a hidden ``.validated`` file,
    a one-line WHITEREF (iqcampy reshapes it to 204 × 512) and results/ with
    REFLECTANCE_ .dat/.hdr/.png and RGBBACKGROUND_/RGBSCENE_/RGBVIEWFINDER_ PNGs.
    The IQ manifest text is not shown there; the Specim manifest of
    GRAS_MANIFEST (same software family) is used with the IQ names.
    """
    import cv2

    cid = "iqcam_2021-02-03_005"
    folder = root / "iqcam_2021-02-03_005_4x-aquarelblauw-FL-01"
    cap = folder / "capture"
    raw, raw_f = bil_counts(lines, samples, bands=204, start=50)
    dark, dark_f = bil_counts(1, samples, bands=204, start=0)
    white, white_f = bil_counts(1, samples, bands=204, start=2000)
    write_pair(cap, cid, iq_header(samples, lines), raw_f)
    write_pair(cap, f"DARKREF_{cid}", iq_header(samples, 1), dark_f)
    write_pair(cap, f"WHITEREF_{cid}", iq_header(samples, 1), white_f)
    refl = ((raw.astype(np.float32) - dark) / (white.astype(np.float32) - dark))
    write_pair(folder / "results", f"REFLECTANCE_{cid}", iq_header(samples, lines, data_type=4),
               refl.transpose(0, 2, 1), ext=".dat", dtype="<f4")
    png = np.zeros((lines, samples, 3), np.uint8)
    for name in (f"{cid}.png", f"results/REFLECTANCE_{cid}.png",
                 f"results/RGBBACKGROUND_{cid}.png", f"results/RGBSCENE_{cid}.png",
                 f"results/RGBVIEWFINDER_{cid}.png"):
        cv2.imwrite(str(folder / name), png)
    (folder / ".validated").write_bytes(b"")
    (folder / "metadata").mkdir()
    (folder / "metadata" / f"{cid}.xml").write_text(
        GRAS_METADATA.replace("gras_ia10", cid).replace(">15<", ">98<"))
    (folder / "manifest.xml").write_text(GRAS_MANIFEST.replace("gras_ia10", cid))
    return folder, cid, raw, dark, white, refl


def test_real_specim_iq_folder(tmp_path):
    from mehs.io import find_captures, read_specim_folder

    folder, cid, raw, dark, white, refl = make_iq_folder(tmp_path)
    cap = read_specim_folder(folder)
    assert cap.capture_id == cid
    np.testing.assert_array_equal(cap.raw.data, raw)
    np.testing.assert_array_equal(cap.darkref.data, dark)
    np.testing.assert_array_equal(cap.whiteref.data, white)
    assert cap.reflectance.data.dtype == np.float32
    np.testing.assert_array_equal(cap.reflectance.data, refl)
    assert cap.reflectance.units == "reflectance"
    np.testing.assert_array_equal(cap.raw.wavelengths, IQ_WAVELENGTHS)
    assert cap.raw.integration_time_ms == 98.0
    assert cap.raw.acquisition_date == "2021-02-03"  # DD-MM-YYYY (the id says 2021-02-03)
    # default bands are 1-based: {70,53,19} → 598.6 / 548.55 / 449.35 nm
    assert [cap.raw.wavelengths[b] for b in cap.raw.default_bands] == [598.6, 548.55, 449.35]
    assert cap.raw.metadata["errors"] == "none" and cap.raw.metadata["fps"] == "10.2041"
    assert cap.preview.shape == (2, 3, 3)
    assert find_captures(tmp_path) == [folder]


def test_real_specim_iq_folder_without_manifest_or_metadata(tmp_path):
    # the capture/ names alone identify the capture (folder name ≠ id)
    from mehs.io import read_specim_folder

    folder, cid, raw, *_ = make_iq_folder(tmp_path)
    (folder / "manifest.xml").unlink()
    (folder / "metadata" / f"{cid}.xml").unlink()
    cap = read_specim_folder(folder)
    assert cap.capture_id == cid and cap.metadata == {}
    np.testing.assert_array_equal(load_cube(folder).data, raw)


def test_written_results_folder_matches_the_iq(tmp_path):
    # results/ as in the iqcampy demo folder, minus the RGB-camera images
    from mehs.io import read_specim_folder, write_specim_folder

    folder, cid, *_ = make_iq_folder(tmp_path / "in")
    out = write_specim_folder(tmp_path / "out" / cid, read_specim_folder(folder))
    names = sorted(p.name for p in (out / "results").iterdir())
    assert names == [f"REFLECTANCE_{cid}.dat", f"REFLECTANCE_{cid}.hdr",
                     f"REFLECTANCE_{cid}.png"]
    assert sorted(p.name for p in (out / "capture").iterdir()) == sorted(
        p.name for p in (folder / "capture").iterdir())
    back = read_specim_folder(out)
    np.testing.assert_array_equal(back.reflectance.data,
                                  read_specim_folder(folder).reflectance.data)


def test_casi_pci_header_big_endian_bip_with_offset(tmp_path):
    # Source: spectralpython/spectral issue #72 (CASI airborne file from geocor):
    # header named <data>.pix.hdr, padded keys ("lines   =", "interleave  ="),
    # 'file type = PCI', big-endian (byte order 1) BIP after an 82432-byte
    # embedded header, braces with inner spaces. (Band names, fwhm and
    # wavelength were skipped in the issue; a wavelength list is added here.)
    header = """ENVI
description = {
    Image File: ../pix_files/CASI_2017_05_18_120034.cc.dc.sl.fss.so.rc.sc.rY.rad_g.pix, created by geocor V:5.6.3 (A) [2017/11/02 15:13:29] }
samples = 3
lines   = 2
bands   = 4
header offset = 82432
file type   = PCI
data type   = 12
interleave  = BIP
sensor type = Unknown
byte order  = 1
read procedures = {pci_read_spatial, pci_read_spectral}
map info = { UTM, 1, 1, 321711.200, 5561737.600,    0.80,    0.80, 33, North, WGS-84 }
pixel size = {   0.800,    0.800, units=meters }
wavelength = { 450.0, 550.0, 650.0, 750.0 }
"""
    cube = (np.arange(2 * 3 * 4) * 257).reshape(2, 3, 4).astype(np.uint16)
    stem = "CASI_2017_05_18_120034.cc.dc.sl.fss.so.rc.sc.rY_g.pix"
    (tmp_path / f"{stem}.hdr").write_text(header)
    (tmp_path / stem).write_bytes(b"\x55" * 82432 + cube.astype(">u2").tobytes())
    for p in (tmp_path / f"{stem}.hdr", tmp_path / stem):
        c = read_envi(p)
        np.testing.assert_array_equal(c.data, cube)
        assert c.data.dtype == np.uint16 and c.data.dtype.isnative
    assert c.metadata["pixel size"] == ["0.800", "0.800", "units=meters"]


def test_load_cube_on_a_results_only_folder(tmp_path):
    # Published IQ data sets ship "plant <N>" folders holding only
    # REFLECTANCE_<id>.dat/.hdr (float32 BIL, 204 bands, acquisition date
    # DD-MM-YYYY, tint) and <id>.png — described in a project's notes on the
    # fire-blight Specim IQ data set (DOI 10.57745/R6AMN3).
    from mehs.errors import InputError

    folder = tmp_path / "plant 1"
    refl = (np.arange(2 * 3 * 204, dtype=np.float32) / 1000).reshape(2, 3, 204)
    write_pair(folder, "REFLECTANCE_2021-03-29_012", iq_header(3, 2, data_type=4),
               refl.transpose(0, 2, 1), ext=".dat", dtype="<f4")
    (folder / "2021-03-29_012.png").write_bytes(b"")  # the preview beside it
    c = load_cube(folder)
    np.testing.assert_array_equal(c.data, refl)
    assert c.units == "reflectance" and c.integration_time_ms == 98.0
    from mehs.cli import main

    assert main(["info", str(folder)]) == 0
    # two results: ambiguous, refused as before
    write_pair(folder, "REFLECTANCE_other", iq_header(3, 2, data_type=4),
               refl.transpose(0, 2, 1), ext=".dat", dtype="<f4")
    with pytest.raises(InputError, match="not a Specim IQ capture"):
        load_cube(folder)
