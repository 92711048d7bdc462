"""Spectral image-based lighting with mehs's HS maps on Mitsuba 3 (optional extra ``render``).

Rooms (imports flow down the list; only ``plugins``, ``scene``, ``run`` and ``demo`` import
Mitsuba, and only when called):

- :mod:`~mehs.render.maps` — read HS environment maps (ENVI, spectral EXR, per-wavelength
  EXR folder), their pseudo-HDR-RGB and SSR up-samplings;
- :mod:`~mehs.render.materials` — thin-film / multilayer reflectance (transfer matrix, Airy),
  optical constants with sources (``data/``);
- :mod:`~mehs.render.plugins` — the Mitsuba plugins: ``HSEnvmap`` (spectral lat-long
  emitter) and ``ThinFilmBSDF``;
- :mod:`~mehs.render.scene` — scenes and renders (spectral and RGB);
- :mod:`~mehs.render.compare` — ΔE2000, relative error, SAM, ×5 difference images;
- :mod:`~mehs.render.page`, :mod:`~mehs.render.run` — ``mehs render``'s outputs;
- :mod:`~mehs.render.demo` — the render step of ``mehs demo``.

See docs/render.md.
"""
