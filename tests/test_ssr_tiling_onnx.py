"""Tiles of an ONNX graph with global average poolings equal the whole image (issue 16).

The graphs are written with the onnx package's helpers (no torch): a 3×3 convolution,
a 2×2 max pooling, a squeeze-and-excitation on the half-resolution map whose scales
depend strongly on the image, nearest up-sampling, and a 3×3 convolution to 31 bands.
"""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from _checks import contrast_rgb

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from mehs.errors import InputError  # noqa: E402
from mehs.ssr.models import OnnxModel  # noqa: E402


def se_graph(path, *, pooling="reducemean", opset=17, other_global=False, seed=0,
             nhwc=False):
    """Write the test graph; ``pooling``: "reducemean" or "gap"; ``other_global``: a
    GlobalMaxPool gate besides the average pooling (not tile-invariant); ``nhwc``:
    NHWC input and output around the NCHW body."""
    rng = np.random.default_rng(seed)
    init = []

    def w(name, *shape, scale=0.5):
        init.append(numpy_helper.from_array(
            (rng.standard_normal(shape) * scale).astype(np.float32), name))
        return name

    def ints(name, values):
        init.append(numpy_helper.from_array(np.array(values, np.int64), name))
        return name

    nodes = [helper.make_node("Transpose", ["rgb"], ["x"], perm=[0, 3, 1, 2])] if nhwc else []
    nodes += [
        helper.make_node("Conv", ["x" if nhwc else "rgb", w("w1", 8, 3, 3, 3), w("b1", 8)],
                         ["c1"], pads=[1, 1, 1, 1]),
        helper.make_node("Relu", ["c1"], ["r1"]),
        helper.make_node("MaxPool", ["r1"], ["d"], kernel_shape=[2, 2], strides=[2, 2]),
        helper.make_node("Conv", ["d", w("w2", 8, 8, 3, 3), w("b2", 8)], ["c2"],
                         pads=[1, 1, 1, 1]),
    ]
    if pooling == "gap":
        nodes.append(helper.make_node("GlobalAveragePool", ["c2"], ["p"]))
    elif opset >= 18:
        nodes.append(helper.make_node("ReduceMean", ["c2", ints("axes", [2, 3])], ["p"],
                                      keepdims=1))
    else:
        nodes.append(helper.make_node("ReduceMean", ["c2"], ["p"], axes=[2, 3], keepdims=1))
    # a gain that keeps the gates off saturation: they swing with the image's means
    nodes += [helper.make_node("Conv", ["p", w("w3", 8, 8, 1, 1, scale=0.1)], ["e"]),
              helper.make_node("Sigmoid", ["e"], ["g"]),
              helper.make_node("Mul", ["c2", "g"], ["a"])]
    last = "a"
    if other_global:
        nodes += [helper.make_node("GlobalMaxPool", ["c2"], ["gm"]),
                  helper.make_node("Conv", ["gm", w("w4", 8, 8, 1, 1, scale=0.1)], ["em"]),
                  helper.make_node("Sigmoid", ["em"], ["gg"]),
                  helper.make_node("Mul", ["a", "gg"], ["am"])]
        last = "am"
    init.append(numpy_helper.from_array(np.array([1, 1, 2, 2], np.float32), "scales"))
    roi = ""
    if opset < 13:                                   # Resize's roi is not optional there
        init.append(numpy_helper.from_array(np.zeros(0, np.float32), "roi"))
        roi = "roi"
    nodes += [helper.make_node("Resize", [last, roi, "scales"], ["u"], mode="nearest"),
              helper.make_node("Add", ["u", "r1"], ["s"]),
              helper.make_node("Conv", ["s", w("w5", 31, 8, 3, 3), w("b5", 31)],
                               ["y" if nhwc else "spectra"], pads=[1, 1, 1, 1])]
    if nhwc:
        nodes.append(helper.make_node("Transpose", ["y"], ["spectra"], perm=[0, 2, 3, 1]))
    shape_in, shape_out = ([1, "h", "w", 3], [1, "h", "w", 31]) if nhwc else \
        ([1, 3, "h", "w"], [1, 31, "h", "w"])
    graph = helper.make_graph(
        nodes, "se", [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, shape_in)],
        [helper.make_tensor_value_info("spectra", TensorProto.FLOAT, shape_out)], init)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


_rgb = contrast_rgb


TILES = {"bytes_per_pixel": 1.0, "max_bytes": 256 * 288}


def _predict(model, rgb, tiling):
    model.tiling = tiling
    return model.predict(rgb)


@pytest.mark.parametrize("pooling,opset,nhwc", [("reducemean", 17, False),
                                                ("reducemean", 18, False),
                                                ("reducemean", 11, False), ("gap", 13, False),
                                                ("reducemean", 17, True)])
def test_onnx_image_means_make_tiles_equal_the_whole_image(tmp_path, pooling, opset, nhwc):
    path = se_graph(tmp_path / "se.onnx", pooling=pooling, opset=opset, nhwc=nhwc)
    rgb = _rgb(256, 640)
    whole = _predict(OnnxModel(path), rgb, "off")
    scale = np.abs(whole).max()
    per_tile = _predict(m_tile := OnnxModel(path), rgb, {**TILES, "statistics": "tile"})
    assert m_tile._tiling_last["summary"]["tiles"] >= 3
    assert np.abs(per_tile - whole).max() > 1e-3 * scale       # what image means are for
    model = OnnxModel(path)
    image = _predict(model, rgb, dict(TILES))                   # the default: "auto"
    assert model._tiling_last["statistics"] == "image"
    assert model._tiling_probe["image_means"] is True
    assert model._tiling_probe["image_means_poolings"] == 1
    assert model._tiling_last["image_runs"] >= 2
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * scale)
    # the rebuilt graph still answers a plain whole-image call as the original does
    np.testing.assert_allclose(_predict(model, rgb, "off"), whole, rtol=1e-6,
                               atol=1e-6 * scale)


def test_onnx_graph_with_another_global_operation_keeps_each_tiles_means(tmp_path):
    path = se_graph(tmp_path / "gmp.onnx", other_global=True)
    rgb = _rgb(256, 640, seed=4)
    whole = _predict(OnnxModel(path), rgb, "off")
    model = OnnxModel(path)
    session = model.session
    # tiles that cannot equal the whole image say so (session 26: 3e-2 off for MST++)
    with pytest.warns(RuntimeWarning, match="tiles use their own statistics"):
        out = _predict(model, rgb, dict(TILES))
    assert model._tiling_last["statistics"] == "tile"
    assert model._tiling_probe["image_means"] is False
    assert model._tiling_probe["image_means_probe_diff"] > 1e-5
    assert model.session is session                 # the original graph is back
    assert out.shape == whole.shape
    with pytest.raises(InputError, match="do not make its tiles equal the whole image"):
        _predict(model, rgb, {**TILES, "statistics": "image"})


def test_onnx_graph_without_poolings_is_tiled_as_before(tmp_path):
    from onnx import save

    path = se_graph(tmp_path / "se.onnx")
    m = onnx.load(str(path))
    # a local graph: the attention's input is the map itself, not its mean
    for n in m.graph.node:
        if n.op_type == "ReduceMean":
            n.op_type, n.input[:] = "Identity", n.input[:1]
            del n.attribute[:]
    save(m, str(tmp_path / "local.onnx"))
    rgb = _rgb(256, 640, seed=5)
    whole = _predict(OnnxModel(tmp_path / "local.onnx"), rgb, "off")
    model = OnnxModel(tmp_path / "local.onnx")
    out = _predict(model, rgb, dict(TILES))
    assert model._tiling_probe["image_means_poolings"] == 0
    assert model._tiling_last["statistics"] == "tile"
    np.testing.assert_allclose(out, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
    with pytest.raises(InputError, match="no global average pooling"):
        _predict(model, rgb, {**TILES, "statistics": "image"})


def test_onnx_tiling_runs_without_torch(tmp_path):
    """The ONNX path must not import torch (the onnx extra does not install it)."""
    path = se_graph(tmp_path / "se.onnx")
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None          # `import torch` fails as if not installed
        import numpy as np
        from mehs.ssr.models import OnnxModel
        sys.path.insert(0, {os.path.dirname(__file__)!r})
        from test_ssr_tiling_onnx import _rgb, TILES
        rgb = _rgb(256, 640)
        m = OnnxModel({str(path)!r})
        m.tiling = "off"
        whole = m.predict(rgb)
        m.tiling = dict(TILES)
        out = m.predict(rgb)
        assert m._tiling_last["statistics"] == "image", m._tiling_last
        assert np.abs(out - whole).max() <= 1e-5 * np.abs(whole).max()
        assert "torch" not in [k for k, v in sys.modules.items() if v is not None]
        print("ok")
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0 and res.stdout.strip().endswith("ok"), res.stderr[-3000:]


def test_owned_cells_follow_the_padded_grid():
    from mehs.ssr.tiling_blend import owned_cells

    assert owned_cells(256, 64, 64, 192, False) == (16, 48)        # 4 px a cell
    assert owned_cells(188, 12, 32, 2 ** 40, True) == (2, 12)      # last tile, padded to 192
    with pytest.raises(InputError, match="do not fall on the owned span"):
        owned_cells(256, 64, 66, 192, False)                       # off the grid
    with pytest.raises(InputError, match="do not fall on the owned span"):
        owned_cells(250, 64, 64, 192, False)                       # an inner tile padded


def test_release_memory_returns_the_arena_before_a_budget_is_measured(tmp_path):
    # the tiling budget is what the process does not hold: an arena kept from a large
    # whole-image run would leave a later tiled call almost none
    def rss():
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    model = OnnxModel(se_graph(tmp_path / "se.onnx"))
    model.tiling = "off"
    model.predict(_rgb(1024, 1024))
    held = rss()
    model.release_memory()
    assert held - rss() > 150 * 2 ** 20          # the run's ~400 MB arena, most of it back
