"""Spectral super-resolution (SSR) evaluation: RGB → 31-band spectra.

Modules
-------
contract    the model contract and the trained-input declaration (bottom of the package)
registry    model names and network architectures; baselines and networks register here
models      :func:`load_model` (names, files, ``module:function``, ``NAME=SPEC``)
baselines   Smits 1999, Mallett & Yuksel 2019, root-polynomial regression
preprocess  Reinhard ``x / (1 + x)`` and its inverse
luminance   luminance restoration ``HS = (X+Y+Z)_rgb / (X+Y+Z)_S · S``
metrics     SAM (degrees), MRAE, RMSE, PSNR per image
data        paired HS/RGB sets (dataset folder or plain folder of pairs)
pipeline    input RGB → (pre-processing) → model → (restoration) → cube
protocol    which settings each model is scored under (its trained input)
scoring     :func:`evaluate`: per-image metrics, summaries
timing      conversion time on a 2048×1024 image (Table 5), CPU and CUDA
results_io  tables and the results folder; ``evaluate`` re-exports all three
report      HTML report with the tables and figures
paper       ``mehs paper``: Tables 1–5 and Figures 9/10 for every registered method
synthetic   small paired sets from measured spectra (tests, demo, benchmarks)
"""
