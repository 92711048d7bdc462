"""mehs's networks under ``torch.compile``: one graph, and the contexts still obeyed.

The layers read per-context state (tiled inference's image-wide statistics, the probes'
plain graph and detached statistics) from ``ContextVar``s, which dynamo cannot trace:
each read broke the compiled graph, although outside tiled inference and the probes
none is ever set. The reads now skip the ``ContextVar`` while no context anywhere has
set it; a context that has still reaches the compiled code (dynamo guards the count).
"""

from __future__ import annotations

import contextvars
import threading

import pytest

torch = pytest.importorskip("torch")
dynamo = pytest.importorskip("torch._dynamo")

from mehs.ssr.net import pooling  # noqa: E402
from mehs.ssr.net.zoo import ARCHITECTURES, build_network  # noqa: E402


@pytest.mark.parametrize("arch", sorted(ARCHITECTURES))
def test_inference_compiles_to_one_graph_with_the_eager_numbers(arch):
    torch.manual_seed(0)
    net = build_network(arch=arch, preset="tiny").eval()
    x = torch.rand(1, 3, 24, 40)
    dynamo.reset()
    with torch.no_grad():
        explained = dynamo.explain(net)(x)
        assert explained.graph_break_count == 0, [str(b.reason)[:200]
                                                  for b in explained.break_reasons]
        want = net(x)
        got = torch.compile(net, backend="eager")(x)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    dynamo.reset()


def test_a_context_set_after_compiling_still_reaches_the_compiled_code():
    def f(x):
        y = x + 1.0 if pooling.plain_graph_wanted() else x
        return y * 2.0 if pooling.statistics_detached() else y

    dynamo.reset()
    g = torch.compile(f, backend="eager", fullgraph=False)
    x = torch.zeros(3)
    assert g(x).tolist() == [0.0] * 3
    with pooling.plain_graph():
        assert g(x).tolist() == [1.0] * 3
        with pooling.detached_statistics():
            assert g(x).tolist() == [2.0] * 3
    assert g(x).tolist() == [0.0] * 3
    assert pooling._PLAIN.users == 0 and pooling._DETACHED.users == 0
    dynamo.reset()


def test_a_context_set_in_one_thread_is_not_seen_in_another():
    entered, leave, seen = threading.Event(), threading.Event(), {}

    def holder():
        with pooling.plain_graph():
            seen["holder"] = pooling.plain_graph_wanted()
            entered.set()
            leave.wait(10)

    t = threading.Thread(target=holder)
    t.start()
    try:
        assert entered.wait(10)
        assert pooling._PLAIN.users == 1
        assert seen["holder"] is True
        assert pooling.plain_graph_wanted() is False         # this thread's own value
    finally:
        leave.set()
        t.join()
    assert pooling._PLAIN.users == 0


def test_the_count_returns_to_zero_when_the_context_raises():
    with pytest.raises(RuntimeError):
        with pooling.detached_statistics():
            raise RuntimeError("inside")
    assert pooling._DETACHED.users == 0 and not pooling.statistics_detached()


def test_a_context_copied_inside_the_with_keeps_its_value_after_it():
    """(an asyncio task started inside and outliving it, found by the review)"""
    with pooling.plain_graph():
        copied = contextvars.copy_context()
    assert pooling._PLAIN.users == 0
    assert copied.run(pooling.plain_graph_wanted) is True
    assert pooling.plain_graph_wanted() is False


def test_the_count_returns_to_zero_when_the_variable_cannot_be_reset():
    cm = pooling.plain_graph()
    contextvars.copy_context().run(cm.__enter__)       # entered in another Context
    with pytest.raises(ValueError):
        cm.__exit__(None, None, None)
    assert pooling._PLAIN.users == 0


def test_tiles_with_image_wide_means_through_a_compiled_network_match_eager():
    """A network compiled outside any context, then run over tiles with the whole
    image's pooling means: the contexts reach the compiled code, the numbers are the
    eager run's (the means' bookkeeping runs outside the compiled graph)."""
    import numpy as np

    from mehs.ssr.tiling_blend import TilingPlan
    from mehs.ssr.tiling_global import predict_tiled_image_means

    torch.manual_seed(0)
    net = build_network(arch="hdrssr", preset="tiny").eval()
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.05 * torch.randn_like(p))
    dynamo.reset()
    compiled = torch.compile(net, backend="eager")

    def run(model):
        def fn(rgb):
            with torch.no_grad():
                t = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None]
                return model(t)[0].permute(1, 2, 0).numpy()
        return fn

    rng = np.random.default_rng(1)
    rgb = (rng.random((48, 64, 3), dtype=np.float32)
           * np.linspace(0.2, 1.5, 64, dtype=np.float32)[None, :, None])
    run(compiled)(rgb[:32, :32])                 # compiled outside any context first
    plan = TilingPlan(tile=32, margin=4, blend=4, align=8)
    eager = predict_tiled_image_means(run(net), rgb, plan)
    got = predict_tiled_image_means(run(compiled), rgb, plan)
    whole = run(net)(rgb)
    scale = float(np.abs(whole).max())
    assert np.abs(got - eager).max() <= 1e-6 * scale
    assert np.abs(got - whole).max() <= np.abs(eager - whole).max() + 1e-6 * scale
    dynamo.reset()
