"""The model contract: registry, module:function specs, factories, ONNX (NCHW / NHWC)."""

import sys
import textwrap

import numpy as np
import pytest

from mehs.errors import InputError
from mehs.rgb import WAVELENGTHS_31
from mehs.ssr.models import MODELS, FunctionModel, list_models, load_model, register_model
from mehs.ssr.pipeline import predict


def test_builtins_registered_and_follow_contract():
    names = list_models()
    assert {"smits", "mallett", "regression"} <= set(names)
    import importlib.util
    if importlib.util.find_spec("torch") and importlib.util.find_spec("mehs.ssr.net.register"):
        assert {"hdrssr", "fcdensenet"} <= set(names)     # the network engineer's hook
    rgb = np.random.default_rng(0).uniform(0, 3, (5, 4, 3)).astype(np.float32)
    for n in ("smits", "mallett"):
        m = load_model(n)
        out = m(rgb)
        assert out.shape == (5, 4, 31) and out.dtype == np.float32
        np.testing.assert_array_equal(m.wavelengths, WAVELENGTHS_31)
    with pytest.raises(InputError, match="train-baseline"):
        load_model("regression")
    with pytest.raises(InputError, match="unknown model"):
        load_model("nope")
    with pytest.raises(InputError, match="shape"):
        load_model("smits")(rgb[..., :2])


def test_register_model_and_reject_duplicates():
    register_model("unit-test-grey", lambda: FunctionModel(
        lambda x: np.repeat(x.mean(-1, keepdims=True), 31, -1), name="unit-test-grey"),
        description="grey", overwrite=True)
    try:
        assert load_model("unit-test-grey").name == "unit-test-grey"
        with pytest.raises(InputError, match="already registered"):
            register_model("unit-test-grey", lambda: None)
        with pytest.raises(InputError):
            register_model("bad:name", lambda: None)
    finally:
        MODELS.pop("unit-test-grey", None)


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    code = textwrap.dedent("""
        import numpy as np

        def grey(rgb):
            return np.repeat(rgb.mean(-1, keepdims=True), 31, -1)

        def wide(rgb):
            return np.repeat(rgb[..., 1:2], 61, -1)
        wide.wavelengths = np.arange(400, 701, 5.0)

        def make(scale=2.0):
            f = lambda rgb: scale * np.repeat(rgb[..., :1], 31, -1)
            return f

        class Model:
            name = "classy"
            wavelengths = np.arange(400, 701, 10.0)
            def __init__(self, k=1.0):
                self.k = k
            def __call__(self, rgb):
                return self.k * np.ones((*rgb.shape[:2], 31), np.float32)

        def broken(rgb):
            return np.full((*rgb.shape[:2], 31), np.nan)
    """)
    (tmp_path / "ssr_user_mod.py").write_text(code)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("ssr_user_mod", None)


def test_module_function_specs(user_module):
    rgb = np.full((2, 3, 3), 0.5, np.float32)
    grey = load_model("ssr_user_mod:grey")
    assert grey.name == "grey" and np.allclose(grey(rgb), 0.5)
    wide = load_model("ssr_user_mod:wide")
    assert wide.wavelengths.size == 61
    # The dataset's 31 bands are picked out of the model's 61.
    assert predict(wide, rgb, restore=False, wavelengths=WAVELENGTHS_31).shape == (2, 3, 31)
    fac = load_model("ssr_user_mod:make", scale=3.0)
    assert np.allclose(fac(rgb), 1.5)
    cls = load_model("ssr_user_mod:Model", k=4.0)
    assert cls.name == "classy" and np.allclose(cls(rgb), 4.0)
    by_file = load_model(f"{user_module / 'ssr_user_mod.py'}:grey")
    assert np.allclose(by_file(rgb), 0.5)
    with pytest.raises(InputError, match="NaN"):
        load_model("ssr_user_mod:broken")(rgb)
    with pytest.raises(InputError, match="has no attribute"):
        load_model("ssr_user_mod:missing")
    with pytest.raises(InputError, match="cannot import"):
        load_model("no_such_module_xyz:f")
    with pytest.raises(InputError, match="lack"):
        predict(wide, rgb, wavelengths=np.array([402.0, 410.0]))


def _onnx_model(path, layout, props=None):
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(5)
    Wm = rng.uniform(0, 1, (3, 31)).astype(np.float32)
    if layout == "NCHW":
        weight = numpy_helper.from_array(Wm.T.reshape(31, 3, 1, 1), "w")
        node = helper.make_node("Conv", ["rgb", "w"], ["spec"])
        x = helper.make_tensor_value_info("rgb", TensorProto.FLOAT, ["N", 3, "H", "W"])
        y = helper.make_tensor_value_info("spec", TensorProto.FLOAT, ["N", 31, "H", "W"])
    else:
        weight = numpy_helper.from_array(Wm, "w")
        node = helper.make_node("MatMul", ["rgb", "w"], ["spec"])
        x = helper.make_tensor_value_info("rgb", TensorProto.FLOAT, ["N", "H", "W", 3])
        y = helper.make_tensor_value_info("spec", TensorProto.FLOAT, ["N", "H", "W", 31])
    graph = helper.make_graph([node], "ssr", [x], [y], initializer=[weight])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    helper.set_model_props(model, {"wavelengths": ",".join(str(v) for v in WAVELENGTHS_31),
                                   **(props or {})})
    onnx.save(model, str(path))
    return Wm


@pytest.mark.parametrize("layout", ["NCHW", "NHWC"])
def test_onnx_models(tmp_path, layout):
    pytest.importorskip("onnxruntime")
    path = tmp_path / f"m_{layout}.onnx"
    Wm = _onnx_model(path, layout)
    m = load_model(str(path))
    assert m.layout == layout and m.name == path.stem
    rgb = np.random.default_rng(6).uniform(0, 2, (6, 5, 3)).astype(np.float32)
    np.testing.assert_allclose(m(rgb), rgb @ Wm, rtol=1e-5)
    np.testing.assert_array_equal(m.wavelengths, WAVELENGTHS_31)


def test_onnx_self_contained_metadata_is_honoured(tmp_path):
    """A graph that applies Reinhard and restores luminance itself gets neither twice."""
    pytest.importorskip("onnxruntime")
    path = tmp_path / "self.onnx"
    Wm = _onnx_model(path, "NCHW", {"mehs_preprocessing": "reinhard",
                                    "mehs_luminance_restored": "true"})
    m = load_model(str(path))
    assert m.preprocessing == "reinhard" and m.restores_luminance is True
    rgb = np.random.default_rng(7).uniform(0, 4, (4, 3, 3)).astype(np.float32)
    # The graph sees the raw RGB whether or not pre-processing is asked for.
    for pp in (False, True):
        np.testing.assert_allclose(predict(m, rgb, preprocess=pp, restore=False), rgb @ Wm,
                                   rtol=1e-5)
    _onnx_model(tmp_path / "plain.onnx", "NCHW")
    plain = load_model(str(tmp_path / "plain.onnx"))
    assert not hasattr(plain, "preprocessing") and not getattr(plain, "restores_luminance", False)


def test_onnx_errors(tmp_path, monkeypatch):
    with pytest.raises(InputError, match="no such ONNX"):
        load_model(str(tmp_path / "missing.onnx"))
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"garbage")
    with pytest.raises(InputError, match="bad.onnx"):
        load_model(str(bad))
    monkeypatch.setitem(sys.modules, "onnxruntime", None)   # simulate the extra missing
    with pytest.raises(InputError, match=r"mehs\[onnx\]"):
        load_model(str(bad))
