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
