"""The render step of ``mehs demo`` (runs only when the ``render`` extra is installed)."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

#: small enough to add only a few seconds to the demo
DEMO_SETTINGS = {"width": 32, "height": 32, "spp": 4, "material": "thin-film:SiO2:300nm"}


def demo_render_step(hs_map: str | Path, out: str | Path, say: Callable[[str], None]) -> str | None:
    """Render a 300 nm SiO₂-on-Si sphere under ``hs_map`` (used as a lat-long map);
    return the page's path, or ``None`` (and say why) when Mitsuba 3 is missing."""
    from mehs.render.scene import RenderSettings, RenderUnavailable, import_mitsuba

    try:
        import_mitsuba()
    except RenderUnavailable as exc:
        say(f"      render: skipped ({exc})")
        return None
    from mehs.render.run import render_comparison

    s = RenderSettings(**DEMO_SETTINGS)
    doc = render_comparison(hs_map, out, s, progress=False)
    page = Path(out) / doc["page"]
    worst = max(doc["results"][1:], key=lambda r: r["mean_delta_E2000"])
    say(f"      render: {s.material} sphere, {s.width}x{s.height}, {s.spp} spp, "
        f"{len(doc['results'])} renders (largest mean ΔE2000: {worst['name']} "
        f"{worst['mean_delta_E2000']:.2f}) → {page.resolve()}")
    return str(page.resolve())
