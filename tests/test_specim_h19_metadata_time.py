"""The integration time of an IQ-layout capture whose header has no ``tint``, from
``metadata/<id>.xml`` in the spellings Specim software writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mehs.io.specim import read_specim_folder


def _folder(root: Path, field: str, value: str) -> Path:
    """An IQ folder (uint16 bil raw + one-line DARKREF, no ``tint`` in the headers) whose
    metadata XML is laid out as Specim's (<properties><header><key field=…>)."""
    cid = "444"
    rng = np.random.default_rng(0)
    (root / "capture").mkdir(parents=True)
    (root / "metadata").mkdir()
    wl = np.linspace(397.32, 1003.58, 4)
    for name, lines in ((cid, 3), (f"DARKREF_{cid}", 1)):
        (root / "capture" / f"{name}.hdr").write_text(
            "ENVI\nfile type = ENVI\nsensor type = SPECIM IQ\n"
            f"samples = 5\nbands = 4\nlines = {lines}\ninterleave = bil\ndata type = 12\n"
            "header offset = 0\nbyte order = 0\n"
            "Wavelength = {" + ", ".join(f"{w:.2f}" for w in wl) + "}\n", encoding="ascii")
        (root / "capture" / f"{name}.raw").write_bytes(
            rng.integers(0, 4096, (lines, 4, 5)).astype("<u2").tobytes())
    (root / "metadata" / f"{cid}.xml").write_text(
        '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n'
        f'<?xml-stylesheet type="text/xsl" href="{cid}.xsl"?>\n'
        '<properties><header><key field="sensor type">SPECIM IQ</key>\n'
        '        <key field="frame rate">50</key>\n'
        f'        <key field="{field}">{value}</key>\n'
        '    </header>\n</properties>\n', encoding="utf-8")
    return root


@pytest.mark.parametrize("field, value, ms", [
    ("integration time", "15", 15.0),             # Specim Lumo (HyperFusion gras_ia10.xml)
    ("Integration Time", "15", 15.0),
    ("integration time", "15 ms", 15.0),
    ("Integration time (us)", "2500", 2.5),
    ("integration_time", "12,5", 12.5),
])
def test_integration_time_from_the_metadata_xml(tmp_path, field, value, ms):
    cap = read_specim_folder(_folder(tmp_path / "444", field, value))
    assert cap.raw.integration_time_ms == pytest.approx(ms)


@pytest.mark.parametrize("value", ["n/a", "0", "-3"])
def test_an_unusable_metadata_time_leaves_none(tmp_path, value):
    cap = read_specim_folder(_folder(tmp_path / "444", "integration time", value))
    assert cap.raw.integration_time_ms is None
