"""Audit of the public SSR dataset splits against the challenges' own folder layouts."""

from __future__ import annotations


import numpy as np

from _checks import write_mat73
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.sources import detect_format, load_source


def _cube(seed: int, h: int = 6, w: int = 5) -> np.ndarray:
    import colour

    sds = list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values())
    refl = np.stack([np.interp(WAVELENGTHS_31, sd.wavelengths, sd.values) for sd in sds])
    return refl[np.random.default_rng(seed).integers(0, 24, (h, w))].astype(np.float32)


def test_ntire2020_and_2018_folders_give_their_splits(tmp_path):
    """The paper's ARAD HS is NTIRE 2020 Track 1 (§3.6.1): NTIRE2020_Train_Spectral/
    ARAD_HS_0001.mat … and NTIRE2020_Validation_Spectral/ARAD_HS_0451.mat (`cube`, `bands`).
    Only a folder name's first word was read ("ntire2020"), so these had no split at all and
    train-ssr trained on the validation scenes the paper tests on."""
    root = tmp_path / "NTIRE2020"
    for i, folder in ((1, "Train"), (2, "Train"), (451, "Validation")):
        write_mat73(root / f"NTIRE2020_{folder}_Spectral" / f"ARAD_HS_{i:04d}.mat",
                     {"cube": _cube(i), "bands": WAVELENGTHS_31[None, :]})
    assert detect_format(root) == "arad1k"  # the same `cube`/`bands` variables
    ps = load_source(root)
    assert ps.splits == {"train": ["ARAD_HS_0001", "ARAD_HS_0002"], "val": ["ARAD_HS_0451"]}
    assert ps[0].hs_array()[0].shape == (6, 5, 31)
    # NTIRE 2018 (BGU-HS): two training folders and a "Validate" one, `rad`
    root = tmp_path / "NTIRE2018"
    for i, folder in ((1, "Train1"), (2, "Train2"), (3, "Validate")):
        write_mat73(root / f"NTIRE2018_{folder}_Spectral" / f"BGU_HS_{i:05d}.mat",
                     {"rad": _cube(i) * 4095, "bands": WAVELENGTHS_31[None, :]})
    ps = load_source(root)
    assert detect_format(root) == "arad"
    assert ps.splits == {"train": ["BGU_HS_00001", "BGU_HS_00002"], "val": ["BGU_HS_00003"]}


def test_train_baseline_does_not_fit_on_the_scored_split_of_a_validation_only_download(
        tmp_path, capsys):
    """ARAD-1K's Valid_Spec folder alone has only a `val` split; `train-baseline` fell back to
    every scene and fitted the regression on the scenes `mehs evaluate --split val` scores."""
    from mehs.cli import main

    root = tmp_path / "ARAD_1K"
    for i in (901, 902):
        write_mat73(root / "Valid_Spec" / f"ARAD_1K_{i:04d}.mat",
                     {"cube": _cube(i, 10, 10), "bands": WAVELENGTHS_31[None, :]})
    assert load_source(root).splits == {"val": ["ARAD_1K_0901", "ARAD_1K_0902"]}
    out = tmp_path / "reg.npz"
    assert main(["train-baseline", str(root), "--out", str(out), "--samples", "200"]) == 2
    err = capsys.readouterr().err
    assert "no 'train' split" in err and "--split all" in err and str(root) in err
    assert not out.exists()
    # asked for explicitly, every scene is used
    assert main(["train-baseline", str(root), "--out", str(out), "--samples", "200",
                 "--split", "all"]) == 0
