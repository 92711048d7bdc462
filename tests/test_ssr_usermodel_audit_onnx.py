"""Audit of user ONNX models in the layouts found in the wild (fixed sizes, float16, ...).

Tiny graphs built with the onnx helper API: a 1×1 convolution RGB → B bands, whose
output is computed here by hand (``einsum``) as the outside truth.
"""

import json

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from mehs.errors import FormatError, InputError  # noqa: E402
from mehs.ssr.contract import trained_for  # noqa: E402
from mehs.ssr.models import load_model  # noqa: E402

RNG = np.random.default_rng(7)
A31 = RNG.random((31, 3)).astype(np.float32)


def save(path, nodes, inputs, outputs, inits=()):
    g = helper.make_graph(nodes, "g", inputs, outputs, list(inits))
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    onnx.save(m, str(path))
    return str(path)


def conv_graph(path, in_shape, out_shape, A=A31, *, in_layout="NCHW", out_layout="NCHW",
               dtype=TensorProto.FLOAT, pre=()):
    """``x`` → 1×1 conv with ``A`` (B×3), input/output transposed to the layouts asked."""
    npdt = {TensorProto.FLOAT16: np.float16, TensorProto.DOUBLE: np.float64}.get(dtype, np.float32)
    nodes, x = list(pre), (pre[-1].output[0] if pre else "x")
    if in_layout == "NHWC":
        nodes.append(helper.make_node("Transpose", [x], ["xt"], perm=[0, 3, 1, 2]))
        x = "xt"
    nodes.append(helper.make_node("Conv", [x, "W"], ["yc"]))
    perm = [0, 2, 3, 1] if out_layout == "NHWC" else [0, 1, 2, 3]
    nodes.append(helper.make_node("Transpose", ["yc"], ["y"], perm=perm))
    w = numpy_helper.from_array(A.reshape(len(A), 3, 1, 1).astype(npdt), "W")
    return save(path, nodes, [helper.make_tensor_value_info("x", dtype, in_shape)],
                [helper.make_tensor_value_info("y", dtype, out_shape)], [w])


def truth(rgb, A=A31):
    return np.einsum("bc,hwc->hwb", A, rgb)


def test_fixed_size_graph_runs_at_its_size_and_refuses_others(tmp_path):
    # a graph exported without dynamic axes (like a 482×512 NTIRE export): the tiler's
    # 256×256 memory probe made it fail even on images of exactly its size
    p = conv_graph(tmp_path / "fixed.onnx", [1, 3, 260, 270], [1, 31, 260, 270])
    m = load_model(p)
    rgb = RNG.random((260, 270, 3)).astype(np.float32)
    np.testing.assert_allclose(m(rgb), truth(rgb), rtol=1e-5, atol=1e-6)
    with pytest.raises(InputError, match=r"260×270 images only.*this one is 40×50"):
        m(rgb[:40, :50])


def test_graph_needing_sizes_divisible_by_8_is_refused_clearly(tmp_path):
    pre = [helper.make_node("SpaceToDepth", ["x"], ["s"], blocksize=8),
           helper.make_node("DepthToSpace", ["s"], ["d"], blocksize=8, mode="DCR")]
    p = conv_graph(tmp_path / "div8.onnx", ["N", 3, "H", "W"], ["N", 31, "H", "W"], pre=pre)
    m = load_model(p)
    ok = RNG.random((24, 32, 3)).astype(np.float32)
    np.testing.assert_allclose(m(ok), truth(ok), rtol=1e-5, atol=1e-6)
    with pytest.raises(InputError, match=r"div8.onnx.*cannot run the graph on a 20×24 image"):
        m(ok[:20, :24])


def test_float16_graph_refuses_hdr_values_beyond_its_range(tmp_path):
    p = conv_graph(tmp_path / "half.onnx", ["N", 3, "H", "W"], ["N", 31, "H", "W"],
                   dtype=TensorProto.FLOAT16)
    m = load_model(p)
    rgb = RNG.random((8, 9, 3)).astype(np.float32)
    y = m(rgb)
    assert y.dtype == np.float32
    np.testing.assert_allclose(y, truth(rgb), rtol=2e-3, atol=2e-3)
    with pytest.raises(InputError, match="float16"):
        m(rgb * 1e5)


def test_double_graph_is_fed_double(tmp_path):
    nodes = [helper.make_node("Cast", ["x"], ["xf"], to=TensorProto.FLOAT),
             helper.make_node("Conv", ["xf", "W"], ["y"])]
    p = save(tmp_path / "f64.onnx", nodes,
             [helper.make_tensor_value_info("x", TensorProto.DOUBLE, ["N", 3, "H", "W"])],
             [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 31, "H", "W"])],
             [numpy_helper.from_array(A31.reshape(31, 3, 1, 1), "W")])
    rgb = RNG.random((5, 6, 3)).astype(np.float32)
    np.testing.assert_allclose(load_model(p)(rgb), truth(rgb), rtol=1e-5)


def test_unusable_inputs_are_refused_at_load(tmp_path):
    p = conv_graph(tmp_path / "b4.onnx", [4, 3, "H", "W"], [4, 31, "H", "W"])
    with pytest.raises(FormatError, match="batch axis is fixed to 4"):
        load_model(p)
    u8 = save(tmp_path / "u8.onnx", [helper.make_node("Cast", ["x"], ["y"], to=TensorProto.FLOAT)],
              [helper.make_tensor_value_info("x", TensorProto.UINT8, ["N", 3, "H", "W"])],
              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", 3, "H", "W"])])
    with pytest.raises(FormatError, match=r"tensor\(uint8\) is not a float"):
        load_model(u8)


def test_band_axis_read_from_the_declared_output_shape(tmp_path):
    # NCHW input, NHWC output: on a 31×31 image (1, 31, 31, 31) fits both readings; the
    # input's layout was taken for the output's, so the cube came back transposed
    rgb = RNG.random((31, 31, 3)).astype(np.float32)
    p = conv_graph(tmp_path / "mixed.onnx", ["N", 3, "H", "W"], ["N", "H", "W", 31],
                   out_layout="NHWC")
    np.testing.assert_allclose(load_model(p)(rgb), truth(rgb), rtol=1e-5, atol=1e-6)
    # nothing declared (a Reshape to its own runtime shape hides it from shape
    # inference): refused rather than guessed
    nodes = [helper.make_node("Conv", ["x", "W"], ["yc"]),
             helper.make_node("Transpose", ["yc"], ["yt"], perm=[0, 2, 3, 1]),
             helper.make_node("Shape", ["yt"], ["s"]), helper.make_node("Reshape", ["yt", "s"], ["y"])]
    q = save(tmp_path / "anon.onnx", nodes,
             [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", 3, "H", "W"])],
             [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["N", "C", "H", "W"])],
             [numpy_helper.from_array(A31.reshape(31, 3, 1, 1), "W")])
    assert load_model(q).output_layout is None
    with pytest.raises(InputError, match="ambiguous"):
        load_model(q)(rgb)
    small = rgb[:31, :20]          # not ambiguous: read as it fits
    np.testing.assert_allclose(load_model(q)(small), truth(small), rtol=1e-5, atol=1e-6)


def test_sidecar_declares_bands_and_training_of_a_foreign_graph(tmp_path):
    A16 = RNG.random((16, 3)).astype(np.float32)
    p = conv_graph(tmp_path / "b16.onnx", ["N", 3, "H", "W"], ["N", 16, "H", "W"], A=A16)
    rgb = RNG.random((6, 7, 3)).astype(np.float32)
    with pytest.raises(InputError, match="16 bands"):
        load_model(p)(rgb)
    wl = np.arange(400, 560, 10.0)
    tf = {"input": "ldr", "preprocessing": None, "output": "spectra"}
    (tmp_path / "b16.onnx.json").write_text(json.dumps({"wavelengths": wl.tolist(),
                                                         "trained_for": tf}))
    m = load_model(p)
    np.testing.assert_array_equal(m.wavelengths, wl)
    got = trained_for(m)
    assert (got.input, got.preprocessing, got.output, got.declared) == ("ldr", None, "spectra", True)
    np.testing.assert_allclose(m(rgb), truth(rgb, A16), rtol=1e-5, atol=1e-6)
    (tmp_path / "b16.onnx.json").write_text(json.dumps({"wavelengths": list(range(400, 701, 10))}))
    with pytest.raises(InputError, match="16 bands, but 31 wavelengths are declared"):
        load_model(p)(rgb)
    (tmp_path / "b16.onnx.json").write_text(json.dumps({"trained_for": {"output": "cube"}}))
    with pytest.raises(FormatError, match=r"b16.onnx.json.*trained_for"):
        load_model(p)
    (tmp_path / "b16.onnx.json").write_text(json.dumps({"bands": 16}))
    with pytest.raises(FormatError, match="b16.onnx.json"):
        load_model(p)
