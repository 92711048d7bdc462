"""The tiling margin and grid of ONNX graphs, measured (issue 16, session 26).

Every ONNX model was tiled with a 64-pixel margin on a 32-pixel grid: a graph with a
wider field, or more poolings, was tiled short of its context or off its grid, and its
tiles differed from whole-image inference near the seams without a word.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
nn, F = torch.nn, torch.nn.functional


class Dilated(nn.Module):
    """Local, no pooling: five 3×3 convolutions dilated by 16, a 80-pixel field."""

    def __init__(self, dilation: int = 16, layers: int = 5):
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(3 if i == 0 else 4, 4, 3, padding=dilation,
                                             dilation=dilation) for i in range(layers))
        self.out = nn.Conv2d(4, 31, 1)

    def forward(self, x):
        for c in self.convs:
            x = torch.tanh(c(x))
        return self.out(x)


def AvgUNet(levels: int):
    """A U-Net of ``levels`` average poolings that pads itself to its grid, 31 bands."""
    from test_ssr_h26_grid import AvgUNet as UNet

    return UNet(levels, bands=31, pad=True)


def _export(net, path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net.eval(), (torch.rand(1, 3, 64, 64),), str(path), dynamo=False,
                          input_names=["rgb"], output_names=["spectra"],
                          dynamic_axes={"rgb": {2: "h", 3: "w"}, "spectra": {2: "h", 3: "w"}})
    return path


def _tiled_and_whole(path, rgb, max_side):
    from mehs.ssr.models import OnnxModel

    model = OnnxModel(path)
    model.tiling = "off"
    whole = model.predict(rgb)
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * max_side ** 2,
                    "statistics": "tile"}
    tiled = model.predict(rgb)
    return tiled, whole, model


def test_a_graph_with_a_field_wider_than_64_pixels_gets_its_margin(tmp_path):
    torch.manual_seed(0)
    path = _export(Dilated(), tmp_path / "dilated.onnx")
    rgb = np.random.default_rng(0).random((320, 700, 3), dtype=np.float32)
    tiled, whole, model = _tiled_and_whole(path, rgb, 320)
    assert model._tiling_last["summary"]["tiles"] >= 3
    assert 64 < model._tiling_probe["margin"] <= 80
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_graph_with_six_poolings_is_tiled_on_its_grid(tmp_path):
    torch.manual_seed(1)
    path = _export(AvgUNet(6), tmp_path / "unet6.onnx")
    rgb = np.random.default_rng(1).random((256, 1024, 3), dtype=np.float32)
    tiled, whole, model = _tiled_and_whole(path, rgb, 288)   # 32-grid tiles: 0.24 off
    assert model._tiling_probe["align"] == 64
    assert model._tiling_last["summary"]["tiles"] >= 2
    np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_the_grid_and_margin_are_kept_per_graph_file(tmp_path, monkeypatch):
    import mehs.ssr.tiling_onnx_probes as probes
    from mehs.ssr.models import OnnxModel

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    torch.manual_seed(2)
    path = _export(Dilated(dilation=4, layers=3), tmp_path / "d.onnx")
    rgb = np.random.default_rng(2).random((256, 600, 3), dtype=np.float32)
    opts = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 200 ** 2}
    first = OnnxModel(path)
    first.tiling = dict(opts)
    first.predict(rgb)
    measured = first._tiling_probe["margin"], first._tiling_probe["align"]
    assert measured == (16, 8)           # three 3×3 convolutions dilated by 4: 12, on the grid
    calls = []
    monkeypatch.setattr(probes, "onnx_margin", lambda *a, **k: calls.append(a) or 0)
    monkeypatch.setattr(probes, "onnx_strides", lambda *a, **k: calls.append(a) or set())
    again = OnnxModel(path)
    again.tiling = dict(opts)
    again.predict(rgb)
    assert (again._tiling_probe["margin"], again._tiling_probe["align"]) == measured
    assert calls == []
    # another graph (other weights: other bytes) is measured afresh
    torch.manual_seed(3)
    other = OnnxModel(_export(Dilated(dilation=4, layers=3), tmp_path / "e.onnx"))
    other.tiling = dict(opts)
    with warnings.catch_warnings():
        # (the stubbed margin of 0 is caught by the check of the tiles on a probe image)
        warnings.simplefilter("ignore", RuntimeWarning)
        other.predict(rgb)
    assert len(calls) == 2


def test_a_field_the_budget_cannot_contain_is_a_lower_bound(tmp_path):
    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_margin
    from mehs.ssr.tiling_probes import FieldWiderThanBudget

    torch.manual_seed(4)
    model = OnnxModel(_export(Dilated(dilation=40, layers=4), tmp_path / "wide.onnx"))  # 160 px
    with pytest.raises(FieldWiderThanBudget) as e:
        onnx_margin(model, 8, max_bytes=2 * 1000 * 256 * 64 + 1, bytes_per_pixel=1000.0)
    assert e.value.lower_bound == 128 and e.value.probe == 256
    assert onnx_margin(model, 8) == 160


def test_a_global_operation_other_than_average_pooling_reads_as_global(tmp_path):
    from test_ssr_tiling_onnx import se_graph

    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_margin
    from mehs.ssr.tiling_probes import GLOBAL_MARGIN

    # the average pooling runs on given means; the max pooling still sees the whole input
    assert onnx_margin(OnnxModel(se_graph(tmp_path / "g.onnx", other_global=True)), 8) \
        == GLOBAL_MARGIN
    assert onnx_margin(OnnxModel(se_graph(tmp_path / "se.onnx")), 8) < GLOBAL_MARGIN


def test_the_strides_follow_the_input_not_the_weights(tmp_path):
    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_strides

    torch.manual_seed(5)
    assert onnx_strides(OnnxModel(_export(AvgUNet(3), tmp_path / "u3.onnx"))) == {2, 4, 8}
    assert onnx_strides(OnnxModel(_export(Dilated(2, 2), tmp_path / "d.onnx"))) == set()


class BrightGate(nn.Module):
    """A 3×3 convolution, plus a wide path open only where the input exceeds 2: dead on
    inputs in [0, 1), 48 px wide on HDR radiance."""

    def __init__(self):
        super().__init__()
        self.near = nn.Conv2d(3, 31, 3, padding=1)
        self.far = nn.Conv2d(3, 31, 3, padding=16, dilation=16)

    def forward(self, x):
        return self.near(x) + self.far(torch.relu(x - 2.0))


def test_a_path_open_only_on_bright_pixels_is_in_the_margin(tmp_path):
    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_margin

    torch.manual_seed(6)
    model = OnnxModel(_export(BrightGate(), tmp_path / "gate.onnx"))
    assert onnx_margin(model, 8) == 16                # not 8: the 1-px convolution's


def test_an_onnx_mstpp_whose_tiles_cannot_equal_the_whole_image_says_so(tmp_path):
    # its channel similarity spans the image and is no average pooling: its tiles were
    # 2.7e-2 of the range off the whole image without a word
    from mehs.ssr.models import OnnxModel
    from mehs.ssr.net import build_network
    from mehs.ssr.net.export import TorchSSRModel, export_onnx

    torch.manual_seed(7)
    net = build_network(arch="mstpp", preset="tiny").eval()
    model = OnnxModel(export_onnx(TorchSSRModel(net, name="m"), tmp_path / "mst.onnx"))
    rgb = np.random.default_rng(7).gamma(1.0, 0.5, (256, 512, 3)).astype(np.float32)
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 256 ** 2}
    with pytest.warns(RuntimeWarning, match="tiles use their own statistics"):
        model.predict(rgb)
    assert model._tiling_last["summary"]["tiles"] >= 2


class TwoOutputs(nn.Module):
    """``aux``: a 1×1 convolution; ``spectra``: the dilated 80-pixel field."""

    def __init__(self):
        super().__init__()
        self.aux = nn.Conv2d(3, 31, 1)
        self.wide = Dilated()

    def forward(self, x):
        return self.aux(x), self.wide(x)


def test_the_probe_cache_tells_the_outputs_of_one_graph_apart(tmp_path, monkeypatch):
    # a margin measured on one output was read back for the other: 1.7e-1 off
    from mehs.ssr.models import OnnxModel

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    torch.manual_seed(8)
    path = tmp_path / "two.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(TwoOutputs().eval(), (torch.rand(1, 3, 64, 64),), str(path),
                          dynamo=False, input_names=["rgb"], output_names=["aux", "spectra"],
                          dynamic_axes={n: {2: "h", 3: "w"} for n in ("rgb", "aux", "spectra")})
    rgb = np.random.default_rng(8).random((320, 700, 3), dtype=np.float32)
    margins = {}
    for out in ("aux", "spectra"):
        model = OnnxModel(path, output=out)
        model.tiling = "off"
        whole = model.predict(rgb)
        model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 320 ** 2}
        tiled = model.predict(rgb)
        margins[out] = model._tiling_probe["margin"]
        np.testing.assert_allclose(tiled, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
    assert margins["aux"] == 0 and margins["spectra"] == 80


def test_the_probe_cache_follows_external_weights(tmp_path, monkeypatch):
    # new weights in the .onnx.data file, the .onnx unchanged: the old margin was reused
    import onnx

    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_file_key

    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    torch.manual_seed(9)
    net = Dilated(dilation=8, layers=2).eval()
    path = tmp_path / "ext" / "net.onnx"
    path.parent.mkdir()

    proto = onnx.load(str(_export(net, tmp_path / "plain.onnx")))
    onnx.save_model(proto, str(path), save_as_external_data=True,
                    all_tensors_to_one_file=True, location="net.onnx.data", size_threshold=0)
    graph = path.read_bytes()
    key = onnx_file_key(OnnxModel(path))
    data = path.parent / "net.onnx.data"
    weights = np.fromfile(data, dtype=np.float32)
    (weights * 2.0).tofile(data)                    # "trained": same sizes and offsets
    assert path.read_bytes() == graph
    assert onnx_file_key(OnnxModel(path)) != key


def test_a_graph_with_sequence_values_is_measured(tmp_path):
    # Shape on a sequence-typed value made onnxruntime refuse the probe's graph
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_grid

    w = numpy_helper.from_array(
        np.random.default_rng(0).normal(size=(31, 3, 3, 3)).astype(np.float32), "W")
    nodes = [helper.make_node("Conv", ["rgb", "W"], ["y"], pads=[1, 1, 1, 1]),
             helper.make_node("SplitToSequence", ["y"], ["seq"], axis=1),
             helper.make_node("ConcatFromSequence", ["seq"], ["spectra"], axis=1)]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, [1, 3, "h", "w"])],
        [helper.make_tensor_value_info("spectra", TensorProto.FLOAT, [1, 31, "h", "w"])], [w])
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    proto.ir_version = 8
    onnx.save(proto, str(tmp_path / "seq.onnx"))
    model = OnnxModel(tmp_path / "seq.onnx")
    assert onnx_grid(model) == 8
    rgb = np.random.default_rng(0).random((256, 600, 3), dtype=np.float32)
    model.tiling = "off"
    whole = model.predict(rgb)
    model.tiling = {"bytes_per_pixel": 1000.0, "max_bytes": 1000 * 256 ** 2}
    np.testing.assert_allclose(model.predict(rgb), whole, rtol=0,
                               atol=1e-5 * np.abs(whole).max())


def test_the_margin_probe_leaves_the_models_session_in_place(tmp_path):
    # it rebuilt the graph on the model itself: another thread's run found the rebuilt
    # session without its feeds ("Required inputs ['mehs_given', …] are missing")
    from test_ssr_tiling_onnx import se_graph

    import mehs.ssr.tiling_onnx as tiling_onnx
    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_margin

    model = OnnxModel(se_graph(tmp_path / "se.onnx"))
    session, outputs, feeds = model.session, model._run_outputs, model._run_feeds
    seen = []
    run = tiling_onnx.OnnxImageMeans.run

    def spy(self, *a, **k):
        seen.append(model.session is session and model._run_feeds is feeds)
        return run(self, *a, **k)

    tiling_onnx.OnnxImageMeans.run = spy
    try:
        onnx_margin(model, 8)
    finally:
        tiling_onnx.OnnxImageMeans.run = run
    assert seen and all(seen)
    assert (model.session, model._run_outputs, model._run_feeds) == (session, outputs, feeds)


def test_a_global_graph_fills_each_strip_length_once(tmp_path, monkeypatch):
    # every strip of a global operation reaches its ends: the first decides, not all 12
    # runs of a length (MST++ tiny: 12.8 s of probes)
    from test_ssr_tiling_onnx import se_graph

    import mehs.ssr.tiling_onnx_probes as probes
    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_probes import GLOBAL_MARGIN

    calls = []
    reach = probes._reach
    monkeypatch.setattr(probes, "_reach", lambda *a, **k: calls.append(a[1]) or reach(*a, **k))
    model = OnnxModel(se_graph(tmp_path / "g.onnx", other_global=True))
    assert probes.onnx_margin(model, 8) == GLOBAL_MARGIN
    assert calls == [256, 512, 1024, 2048]


def test_a_graph_onnxruntime_optimised_into_contrib_operators_keeps_its_grid(tmp_path):
    # onnx cannot type com.microsoft::FusedConv: the values behind it were left out of
    # the grid probe (8 for a grid of 64, tiles 8.5e-5 off)
    import onnxruntime as ort

    from mehs.ssr.models import OnnxModel
    from mehs.ssr.tiling_onnx_probes import onnx_grid

    torch.manual_seed(10)
    plain = _export(AvgUNet(6), tmp_path / "u6.onnx")
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    so.optimized_model_filepath = str(tmp_path / "u6_opt.onnx")
    ort.InferenceSession(str(plain), sess_options=so, providers=["CPUExecutionProvider"])
    import onnx

    assert any(n.domain == "com.microsoft" for n in onnx.load(so.optimized_model_filepath).graph.node)
    assert onnx_grid(OnnxModel(so.optimized_model_filepath)) == 64
