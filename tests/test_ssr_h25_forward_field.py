"""The receptive-field probe measures in forward mode where its gradient does not fit.

The autograd probe keeps every layer's output (~24× an inference's memory): under the
default 2 GB cap MST++'s full preset, whose 112-px field needs a 256² probe, stopped at
128², warned twice per call, tiled with a 64-px lower bound (tiles then differ from the
whole image near their seams) and probed again on every call. A Jacobian-vector product
holds one layer's output and its tangent at a time; read per grid phase, it gives the
gradient probe's margin exactly.
"""

import warnings

import numpy as np
import pytest
from _checks import contrast_rgb

torch = pytest.importorskip("torch")

from mehs.ssr.net import build_network  # noqa: E402
from mehs.ssr.tiling_probes import (_forward_mode_margin, torch_align,  # noqa: E402
                                    torch_receptive_radius)
from mehs.ssr.tiling_torch import tiled_torch_call  # noqa: E402


class _Phased(torch.nn.Module):
    """A strided convolution and a transposed one: the field depends on the grid phase."""

    def __init__(self):
        super().__init__()
        self.down = torch.nn.Conv2d(3, 4, 5, stride=2, padding=2)
        self.mid = torch.nn.Conv2d(4, 4, 3, padding=1)
        self.up = torch.nn.ConvTranspose2d(4, 3, 4, stride=2, padding=1)
        self.tail = torch.nn.Conv2d(3, 2, (1, 3), padding=(0, 1))

    def forward(self, x):
        return self.tail(self.up(torch.tanh(self.mid(torch.tanh(self.down(x))))))


@pytest.mark.parametrize("case", ["mstpp", "hdrssr", "phased"])
def test_forward_mode_margin_equals_the_gradient_probes(case):
    torch.manual_seed(1)
    if case == "phased":
        net, a = _Phased().eval(), 2
    else:                # hdrssr: its inference writes out= and in strips (plain_graph)
        net = build_network(arch=case, preset="tiny").eval()
        a = torch_align(net)
    with torch.enable_grad():
        grad = torch_receptive_radius(net, probe=128, max_probe=256, align=a)
    for probe in (128, 256):
        margin, held = _forward_mode_margin(net, probe, a, "cpu")
        if margin is not None:
            break
    assert margin == grad and held > 0, (margin, grad)
    assert grad > 0


def _wide_attention():
    """A 72-pixel receptive radius (24 3×3 convolutions dilated by 3), one channel attention."""
    from test_ssr_h23_lean_inference import _WideAttention

    return _WideAttention(layers=24, dilation=3)


def test_a_field_the_gradient_cannot_afford_is_measured_and_tiles_equal_the_whole_image():
    from types import SimpleNamespace

    torch.manual_seed(8)
    net = _wide_attention().eval()
    # 16 MiB: after the 128² probes (gradient 5.4 MB, forward mode 2.0 MB held) the 256²
    # gradient probe does not fit, the forward-mode one does; 1200 B/px make tiles of
    # ~14k pixels, two or more along a 40×480 image
    model = SimpleNamespace(network=net, device="cpu", name="wide",
                            tiling=dict(bytes_per_pixel=1200.0, max_bytes=16 << 20,
                                        statistics="image", blend=8))
    rgb = contrast_rgb(40, 480, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)    # no lower-bound warning
        tiled = tiled_torch_call(model, rgb)
    assert model._tiling_probe["margin"] == 72              # 72 px, on the 8-px grid
    assert not model._tiling_probe.get("margin_bound")
    assert model._tiling_last["summary"]["tiles"] >= 2
    with torch.no_grad():
        whole = net(torch.from_numpy(rgb.transpose(2, 0, 1).copy())[None])[0]
    whole = whole.permute(1, 2, 0).numpy()
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_network_without_forward_mode_derivatives_keeps_the_lower_bound():
    from mehs.ssr.tiling_probes import FieldWiderThanBudget

    class _NoForward(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.clone()

        @staticmethod
        def backward(ctx, g):
            return g

    class _Net(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.convs = torch.nn.ModuleList(torch.nn.Conv2d(3, 3, 3, padding=1)
                                             for _ in range(20))

        def forward(self, x):
            for c in self.convs:
                x = torch.tanh(c(x))
            return _NoForward.apply(x)

    torch.manual_seed(0)
    with pytest.raises(FieldWiderThanBudget) as e:
        torch_receptive_radius(_Net(), probe=32, max_probe=128, max_bytes=1 << 20)
    assert e.value.lower_bound == 16 and e.value.probe == 32


def test_a_bound_is_kept_until_a_budget_can_measure_the_field(tmp_path, monkeypatch):
    # a field no probe the budget allows can measure was probed again by every call of
    # every process (the full paper network: now a gradient and two forward-mode probes)
    from types import SimpleNamespace

    import mehs.ssr.tiling_torch as tiling

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    calls = []
    real = tiling.torch_receptive_radius

    def counted(*a, **k):
        calls.append(k.get("max_bytes"))
        if k["max_bytes"] >= 1 << 34:
            return 64          # what the 256² probe measures (see the test above), 20 s sooner
        return real(*a, **k)

    monkeypatch.setattr(tiling, "torch_receptive_radius", counted)
    torch.manual_seed(3)
    # a 3-block bottleneck: a 64-px field, which a 128² probe cannot resolve
    net = build_network(arch="mstpp", preset="tiny", levels=2, num_blocks=(1, 3, 1)).eval()
    rgb = contrast_rgb(16, 400, seed=5)

    def model(max_bytes):
        # tiles of 16 × 320 pixels whatever the budget
        return SimpleNamespace(network=net, device="cpu", name="mst",
                               tiling=dict(bytes_per_pixel=max_bytes / (16 * 320),
                                           max_bytes=max_bytes, statistics="image", blend=8))

    for _ in range(2):                     # the second call reads the bound back
        m = model(16 * 320)
        with pytest.warns(RuntimeWarning, match="wider than a 128-pixel probe"):
            tiled_torch_call(m, rgb)
        assert len(calls) == 1
        assert m._tiling_probe["margin"] == 64 and m._tiling_probe["margin_bound"]
    stored = next(tmp_path.rglob("*.json")).read_text()
    assert '"margin_bound"' in stored and '"lower_bound": 64' in stored
    roomy = model(1 << 34)                 # holds the 256² gradient probe: probed again
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        tiled_torch_call(roomy, rgb)
    assert len(calls) == 2
    assert roomy._tiling_probe["margin"] == 64 and not roomy._tiling_probe.get("margin_bound")
