"""Image-wide means' runs over the tiles keep one stitched output, not the last run's and
the next one's (issue 16: 0.26 GB more for a 2048×1024 image from the third run on)."""

import gc
import weakref
from types import SimpleNamespace

import pytest

torch = pytest.importorskip("torch")

from _checks import contrast_rgb  # noqa: E402

from mehs.ssr import tiling_global  # noqa: E402
from mehs.ssr.net import build_network  # noqa: E402
from mehs.ssr.net.layers import ChannelAttention  # noqa: E402
from mehs.ssr.tiling_torch import tiled_torch_call  # noqa: E402


def test_the_runs_over_the_tiles_hold_one_output(monkeypatch):
    torch.manual_seed(0)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, ChannelAttention):     # image-dependent means: several runs
                m.squeeze.weight.mul_(20.0)
                m.excite.weight.mul_(20.0)
    made, alive_at_start = [], []
    real = tiling_global.predict_tiled

    def watched(*args, **kwargs):
        gc.collect()
        alive_at_start.append(sum(r() is not None for r in made))
        out = real(*args, **kwargs)
        made.append(weakref.ref(out))
        return out

    monkeypatch.setattr(tiling_global, "predict_tiled", watched)
    model = SimpleNamespace(network=net, device="cpu", name="hdrssr",
                            tiling=dict(bytes_per_pixel=1.0, max_bytes=64 * 128, blend=16,
                                        statistics="image"))
    tiled_torch_call(model, contrast_rgb(64, 600))
    assert model._tiling_last["image_runs"] >= 3, model._tiling_last
    assert alive_at_start == [0] * len(alive_at_start)
