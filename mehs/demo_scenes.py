"""The scenes of ``mehs demo``: natural scenes from measured spectra, and their pools.

Kept apart from :mod:`mehs.demo` (the pipeline) so the scene list can grow without the
pipeline module growing with it.
"""

from __future__ import annotations

from dataclasses import dataclass

from mehs.errors import InputError


@dataclass(frozen=True)
class DemoScene:
    """One simulated scene of the demo.

    ``kind`` ``"natural"``: :func:`mehs.scenes.natural.make_natural_scene` with ``lighting``
    (the pool, train or test, is chosen by :func:`run_demo` from the split the scene will fall
    in); other kinds: :func:`mehs.capture.scene.make_scene` with ``illuminant`` and
    ``light_source``.
    """

    scene_id: str
    kind: str
    illuminant: str | None
    light_source: str | None
    source_ratio: float
    motion: bool
    description: str
    lighting: str | None = None


_FEATURED = (
    DemoScene("s01_sodium_lamp", "natural", None, None, 300.0, False,
              "street at night lit by high-pressure sodium, the lamp in view", "sodium"),
    DemoScene("s02_moving_cloud", "natural", None, None, 300.0, True,
              "daylight scene with a bright cloud drifting between exposures", "daylight"),
    DemoScene("s03_daylight", "natural", None, None, 1000.0, False,
              "sun and sky (CIE D series), cast shadows, the sun's glare in view", "daylight"),
    DemoScene("s04_window", "natural", None, None, 300.0, False,
              "room under a lamp with daylight from a window in view", "mixed"),
    DemoScene("s05_tungsten", "natural", None, None, 1000.0, False,
              "room under tungsten light, the bulb in view", "tungsten"),
    DemoScene("s06_fluorescent", "natural", None, None, 300.0, False,
              "room under fluorescent tubes, a tube in view", "fluorescent"),
)
_MORE_LIGHTINGS = ("led", "daylight", "mixed", "sodium", "tungsten", "fluorescent")


def demo_scenes(n: int) -> list[DemoScene]:
    """The first ``n`` demo scenes: the sodium-lamp scene, the moving scene, then varied light."""
    if n < 1:
        raise InputError(f"--scenes must be at least 1, got {n}")
    out = list(_FEATURED[:n])
    for i in range(len(out), n):
        light = _MORE_LIGHTINGS[(i - len(_FEATURED)) % len(_MORE_LIGHTINGS)]
        out.append(DemoScene(f"s{i + 1:02d}_{light}", "natural", None, None, 300.0, False,
                             f"natural scene, {light} lighting", light))
    return out


def demo_pools(specs: list[DemoScene], seed: int, splits=(0.5, 0.0, 0.5)) -> dict[str, str]:
    """The material/light pool of each scene: the split it will fall in.

    The builder splits the *passing* scenes by :func:`mehs.dataset.splits.make_splits`; the
    moving scene fails the ghost rule, so the split of the others is known before capture and
    each is drawn from its split's pool (test scenes: materials and lights never trained on).
    """
    from mehs.dataset.splits import make_splits

    still = [s.scene_id for s in specs if not s.motion]
    split_of = {sid: name for name, ids in make_splits(still, splits, seed).items()
                for sid in ids}
    return {s.scene_id: ("val" if s.motion else split_of[s.scene_id]) for s in specs}
