"""Spectral super-resolution (SSR) evaluation: RGB → 31-band spectra.

Modules
-------
models      the model contract, the registry and :func:`load_model`
baselines   Smits 1999, Mallett & Yuksel 2019, root-polynomial regression
preprocess  Reinhard ``x / (1 + x)`` and its inverse
luminance   luminance restoration ``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S``
metrics     SAM (degrees), MRAE, RMSE, PSNR per image
data        paired HS/RGB sets (dataset folder or plain folder of pairs)
pipeline    input RGB → (pre-processing) → model → (restoration) → cube
evaluate    scoring, per-image results and paper-style tables
report      HTML report with the tables and figures
synthetic   small paired sets from measured spectra (tests, demo, benchmarks)
"""
