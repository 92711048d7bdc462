"""The tiling probes of mehs's networks are measured once per architecture (issue 16)."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from mehs.ssr import tiling_torch as tiling  # noqa: E402
from mehs.ssr.allocator import allocator_overhead  # noqa: E402
from mehs.ssr.probe_cache import ProbeStore, network_key  # noqa: E402


def _net(growth=4, seed=2):
    from mehs.ssr.net import build_network

    torch.manual_seed(seed)
    return build_network(variant="fcdensenet", first_channels=8, down_layers=(1, 1, 1),
                         bottleneck_layers=1, growth=growth).eval()


def _rgb(h=120, w=176):
    return np.random.default_rng(3).gamma(1.0, 1.0, (h, w, 3)).astype(np.float32)


def _tiled(net, budget):
    m = SimpleNamespace(network=net, device="cpu", tiling={"max_bytes": budget})
    return m, tiling.tiled_torch_call(m, _rgb())


@pytest.fixture
def counted(monkeypatch, tmp_path):
    """The cache in tmp_path; counts of the memory and margin probes actually run."""
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path / "cache"))
    calls = {"memory": 0, "margin": 0}
    mem, rad = tiling.torch_memory_probe, tiling.torch_receptive_radius

    def memory(*a, **k):
        calls["memory"] += 1
        return mem(*a, **k)

    def radius(*a, **k):
        calls["margin"] += 1
        return rad(*a, **k)

    monkeypatch.setattr(tiling, "torch_memory_probe", memory)
    monkeypatch.setattr(tiling, "torch_receptive_radius", radius)
    return calls


def _budget(net):
    m = tiling.torch_memory_probe(net)
    n = 96 * 96
    return int(allocator_overhead(n) * (m["fixed_bytes"] + m["bytes_per_pixel"] * n))


def test_a_second_model_of_the_same_architecture_reads_the_probes(counted, tmp_path):
    net = _net()
    budget = _budget(net)
    counted["memory"] = 0
    m1, out1 = _tiled(net, budget)
    assert counted == {"memory": 1, "margin": 1}
    assert m1._tiling_last["plan"].tile is not None          # really tiled
    files = list((tmp_path / "cache" / "tiling").glob("*.json"))
    assert len(files) == 1
    doc = json.loads(files[0].read_text())
    assert set(doc["probes"]) == {"memory", "margin", "align"}
    # another process would build the same network with other weights: no probe runs
    m2, out2 = _tiled(_net(seed=7), budget)
    assert counted == {"memory": 1, "margin": 1}
    assert m2._tiling_probe["margin"] == m1._tiling_probe["margin"]
    assert m2._tiling_last["plan"] == m1._tiling_last["plan"]
    # and with the first network's weights, the same numbers as the measured run
    _, out3 = _tiled(_net(), budget)
    np.testing.assert_array_equal(out3, out1)


def test_another_architecture_or_chunking_is_measured_again():
    from mehs.ssr.net.zoo import build_network

    assert network_key(_net(growth=4)) != network_key(_net(growth=6))
    assert network_key(_net(seed=1)) == network_key(_net(seed=5))       # weights do not count
    net = build_network(arch="hdrssr", preset="tiny")
    key = network_key(net)
    chunked = [m for m in net.modules() if isinstance(getattr(m, "chunk_pixels", None), int)]
    assert chunked
    chunked[0].chunk_pixels = 1234
    assert network_key(net) != key


def test_user_networks_and_a_disabled_cache_are_not_stored(monkeypatch, tmp_path):
    class Mine(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.c = torch.nn.Conv2d(3, 4, 3, padding=1)

        def forward(self, x):
            return self.c(x)

    assert network_key(Mine()) is None
    monkeypatch.setenv("MEHS_CACHE_DIR", str(tmp_path))
    store = ProbeStore.for_network(Mine())
    store.put("margin", 3)
    assert store.get("margin") is None and not list(tmp_path.rglob("*.json"))
    monkeypatch.setenv("MEHS_CACHE_DIR", "")
    store = ProbeStore.for_network(_net())
    store.put("margin", 3)
    assert store.get("margin") is None and not list(tmp_path.rglob("*.json"))


@pytest.mark.parametrize("damage", ["not json", '{"format": "mehs-tiling-probe/1"}',
                                    "wrong key", "wrong type"])
def test_a_damaged_entry_is_measured_again_and_rewritten(counted, tmp_path, damage):
    net = _net()
    store = ProbeStore.for_network(net)
    store.put("margin", 24)
    text = store.path.read_text()
    doc = json.loads(text)
    if damage == "wrong key":
        doc["key"] = "0" * 64
        text = json.dumps(doc)
    elif damage == "wrong type":
        doc["probes"]["margin"] = "24"
        text = json.dumps(doc)
    elif damage != "not json":
        text = damage
    else:
        text = text[:10]
    store.path.write_text(text)
    fresh = ProbeStore.for_network(net)
    assert fresh.get("margin") is None
    fresh.put("margin", 24)
    assert ProbeStore.for_network(net).get("margin") == 24
