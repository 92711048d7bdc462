"""HDR synthesis: response recovery, merging, ghosts, resampling.

- :mod:`mehs.synthesis.bracket` — :class:`Bracket`, :func:`load_bracket` (scene folder or Specim IQ folders).
- :mod:`mehs.synthesis.response` — :class:`ResponseCurve`, :func:`recover_response_Debevec1997`, :func:`sample_pixels`.
- :mod:`mehs.synthesis.merge` — :data:`MERGE_METHODS`, :func:`merge_bracket`, :class:`NoiseModel`.
- :mod:`mehs.synthesis.ghost` — :func:`detect_ghosts`, :func:`deghost_from_reference`.
- :mod:`mehs.synthesis.fuse` — :func:`fuse_bracket`, :func:`write_fusion` (``mehs fuse``).
- :mod:`mehs.synthesis.resample` — band resampling to 31 bands.

Submodules are imported on demand so that ``import mehs`` stays light.
"""
