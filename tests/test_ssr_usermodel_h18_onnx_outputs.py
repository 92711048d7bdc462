"""ONNX user models with several outputs: the spectra output is named, found, or refused.

The graphs are written with ``onnx.helper``; the truth is numpy's 1×1 convolution of the
input (a band-by-channel matrix), so a model reading another output than the spectra
shows as a wrong number or an error, never as a plausible score.
"""

import json

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from mehs.errors import FormatError  # noqa: E402
from mehs.ssr.models import load_model  # noqa: E402

A = (np.random.default_rng(18).random((31, 3)) * 0.5 + 0.05).astype(np.float32)


def two_output_graph(path, *, first="feat", feat_bands=31):
    """Outputs, in this order: ``first`` (a ``feat_bands``-channel map: 2·A·x, a feature map
    the network computes before halving it) and ``spectra`` (A·x); ``first="aux"`` makes it
    a one-channel map instead."""
    bands = 1 if first == "aux" else feat_bands
    w2 = numpy_helper.from_array((2 * A[:bands] if first == "feat" else
                                  np.ones((1, 3), np.float32)).reshape(bands, 3, 1, 1), "w2")
    w = numpy_helper.from_array(A.reshape(31, 3, 1, 1), "w")
    nodes = [helper.make_node("Conv", ["x", "w2"], [first]),
             helper.make_node("Conv", ["x", "w"], ["spectra"])]
    g = helper.make_graph(
        nodes, "two", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3, "H", "W"])],
        [helper.make_tensor_value_info(first, TensorProto.FLOAT, ["N", bands, "H", "W"]),
         helper.make_tensor_value_info("spectra", TensorProto.FLOAT, ["N", 31, "H", "W"])],
        [w2, w])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 13)])
    m.ir_version = 8
    onnx.save(m, str(path))
    return path


def truth(rgb):
    return np.einsum("bc,hwc->hwb", A, rgb)


RGB = np.random.default_rng(1).random((6, 7, 3)).astype(np.float32)


def test_two_cube_shaped_outputs_are_refused_unless_one_is_named(tmp_path):
    # the first output, a 31-channel feature map, was scored as the spectra (twice the truth)
    path = two_output_graph(tmp_path / "m.onnx")
    with pytest.raises(FormatError, match=r"2 outputs .*'feat'.*'spectra'.* several could hold"):
        load_model(str(path))
    m = load_model(str(path), output="spectra")
    np.testing.assert_allclose(m(RGB), truth(RGB), rtol=1e-5, atol=1e-6)
    assert m.output_name == "spectra"


def test_sidecar_names_the_spectra_output(tmp_path):
    path = two_output_graph(tmp_path / "m.onnx")
    (tmp_path / "m.onnx.json").write_text(json.dumps({"output": "spectra"}))
    np.testing.assert_allclose(load_model(str(path))(RGB), truth(RGB), rtol=1e-5, atol=1e-6)
    # the keyword wins over the sidecar
    np.testing.assert_allclose(load_model(str(path), output="feat")(RGB), 2 * truth(RGB),
                               rtol=1e-5, atol=1e-6)


def test_unknown_output_name_lists_the_graph_outputs(tmp_path):
    path = two_output_graph(tmp_path / "m.onnx")
    (tmp_path / "m.onnx.json").write_text(json.dumps({"output": "spectrum"}))
    with pytest.raises(FormatError, match=r"no output 'spectrum' \(its outputs: 'feat'"):
        load_model(str(path))
    (tmp_path / "m.onnx.json").write_text(json.dumps({"output": 3}))
    with pytest.raises(FormatError, match="'output' must be the name"):
        load_model(str(path))


def test_the_one_cube_shaped_output_is_taken_after_an_auxiliary_map(tmp_path):
    # (N, 1, H, W) first, the spectra second: the first was taken, and the model refused
    path = two_output_graph(tmp_path / "aux.onnx", first="aux")
    m = load_model(str(path))
    assert m.output_name == "spectra"
    np.testing.assert_allclose(m(RGB), truth(RGB), rtol=1e-5, atol=1e-6)


def test_output_key_is_refused_for_a_torchscript_model(tmp_path):
    torch = pytest.importorskip("torch")
    net = torch.nn.Conv2d(3, 31, 1)
    torch.jit.script(net.eval()).save(str(tmp_path / "n.pt"))
    (tmp_path / "n.pt.json").write_text(json.dumps({"output": "spectra"}))
    with pytest.raises(FormatError, match="not an ONNX graph"):
        load_model(str(tmp_path / "n.pt"))


def test_tiled_image_means_read_the_spectra_output_of_a_multi_output_graph(tmp_path):
    # the image-means graph took get_outputs()[0] for the spectra: here an 8-channel map
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_ssr_tiling_onnx import TILES, _predict, _rgb, se_graph

    path = se_graph(tmp_path / "se.onnx")
    m = onnx.load(str(path))
    first = helper.make_tensor_value_info("r1", TensorProto.FLOAT, [1, 8, "h", "w"])
    outs = [first] + list(m.graph.output)
    del m.graph.output[:]
    m.graph.output.extend(outs)
    onnx.save(m, str(tmp_path / "two.onnx"))
    rgb = _rgb(256, 640)
    whole = _predict(load_model(str(path)), rgb, "off")
    model = load_model(str(tmp_path / "two.onnx"))
    assert model.output_name == "spectra"
    np.testing.assert_allclose(_predict(model, rgb, "off"), whole, rtol=1e-6,
                               atol=1e-6 * np.abs(whole).max())
    image = _predict(model, rgb, dict(TILES))
    assert model._tiling_last["statistics"] == "image"
    np.testing.assert_allclose(image, whole, rtol=0, atol=1e-5 * np.abs(whole).max())
