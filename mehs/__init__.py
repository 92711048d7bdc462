"""mehs — high dynamic range hyperspectral datasets from a line-scan camera.

The package is organised by pipeline stage:

- :mod:`mehs.io` — ENVI cubes, Specim IQ capture folders, OpenEXR, atomic writes.
- :mod:`mehs.capture` — simulated scene/sensor, serial drivers, bracketed capture sessions.
- :mod:`mehs.synthesis` — response recovery, HDR merging, ghost detection, resampling.
- :mod:`mehs.rgb` — spectra → XYZ → linear sRGB (pseudo-HDR-RGB, LDR-RGB, previews).
- :mod:`mehs.dataset` — the ME HS dataset builder and its report.
- :mod:`mehs.ssr` — spectral super-resolution models, metrics and evaluation.
"""

__version__ = "0.1.0"

from mehs.errors import MehsError  # noqa: E402,F401
from mehs.cube import SpectralCube  # noqa: E402,F401
