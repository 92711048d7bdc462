"""Capture: simulated scene/sensor, serial device drivers and bracketed capture sessions.

- :mod:`mehs.capture.scene` — :func:`make_scene`, :class:`Scene`, the Specim IQ band grid.
- :mod:`mehs.capture.sensor` — :class:`SensorModel` (QE, noise, FPN, response, 12-bit ADC).
- :mod:`mehs.capture.simulate` — :func:`simulate_bracket`, :func:`write_simulated_scene`.
- :mod:`mehs.capture.transport` — pyserial ports with terminator/disconnect checks.
- :mod:`mehs.capture.zaber` — Zaber ASCII stage driver; :mod:`mehs.capture.camera` — line camera driver.
- :mod:`mehs.capture.simdevice` — simulated stage + camera on loopback TCP or ptys, fault injection.
- :mod:`mehs.capture.session` — :func:`capture_scene`, :func:`auto_exposure`.
- :mod:`mehs.capture.scenefolder` — the ``mehs-scene/1`` folder (scene.json, exposures).
- :mod:`mehs.capture.fakeport` — scripted port for byte-exact protocol tests.

Submodules are imported on demand (the package import stays light for the CLI).
"""
