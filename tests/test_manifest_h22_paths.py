"""A hand-edited or hostile dataset manifest cannot point mehs outside the dataset: scene ids
name folders that builds replace and remove, and file entries are read and hashed."""

import json

import numpy as np
import pytest

from mehs.cube import SpectralCube
from mehs.dataset.build import build_from_hs
from mehs.dataset.manifest import read_manifest
from mehs.errors import FormatError
from mehs.io.envi import write_envi


@pytest.fixture
def dataset(tmp_path):
    write_envi(tmp_path / "in" / "c.hdr",
               SpectralCube(np.full((3, 4, 31), 0.5, np.float32), np.arange(400.0, 701.0, 10.0)),
               dtype=np.float32)
    ds = tmp_path / "ds"
    build_from_hs([tmp_path / "in" / "c.hdr"], ds, workers=1, progress=False)
    return ds


@pytest.mark.parametrize("field, value", [
    ("id", "../outside"), ("id", ".hidden"), ("id", "a/b"),
    ("hs", "../../etc/passwd"), ("hs", "/etc/passwd"), ("hs", "scenes/../../x.hdr"),
])
def test_manifest_entries_outside_the_dataset_are_refused(dataset, field, value):
    doc = json.loads((dataset / "manifest.json").read_text())
    if field == "id":
        doc["scenes"][0]["id"] = value
    else:
        doc["scenes"][0]["files"][field] = value
    (dataset / "manifest.json").write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="manifest|id|inside the dataset"):
        read_manifest(dataset)


def test_a_built_manifest_reads(dataset):
    assert read_manifest(dataset)["scenes"][0]["id"] == "c"


def test_a_scene_id_with_a_trailing_newline_is_refused():
    from mehs.dataset.scene_list import check_scene_id
    from mehs.errors import InputError

    with pytest.raises(InputError, match="folder name"):
        check_scene_id("s1\n")
    assert check_scene_id("s1.v2_a-b") == "s1.v2_a-b"
