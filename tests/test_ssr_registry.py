"""The registry at the bottom of mehs.ssr: import direction, and the architecture contract
(a checkpoint records arch + preset + trained_for; the loader dispatches through the registry)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mehs.errors import FormatError, InputError

#: A tiny network, in the keywords both the first release and the model zoo accept.
TINY = dict(first_channels=8, down_layers=(1, 1), bottleneck_layers=1, growth=8)


def test_bottom_modules_import_nothing_above_them():
    code = ("import sys, mehs.ssr.registry, mehs.ssr.contract; "
            "print([m for m in ('mehs.ssr.models', 'mehs.ssr.baselines', 'mehs.ssr.net', "
            "'mehs.ssr.scoring', 'torch') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_registered_architecture_loads_from_its_checkpoint(tmp_path):
    torch = pytest.importorskip("torch")
    from mehs.io.atomic import atomic_path
    from mehs.rgb import WAVELENGTHS_31
    from mehs.ssr.contract import TrainedFor, trained_for
    from mehs.ssr.evaluate import evaluate
    from mehs.ssr.models import load_model
    from mehs.ssr.net.train import CHECKPOINT_FORMAT
    from mehs.ssr.preprocess import Preprocessing
    from mehs.ssr.registry import ARCHITECTURES, Architecture, get_architecture, register_architecture
    from mehs.ssr.synthetic import make_paired_set

    class Lin(torch.nn.Module):
        """1×1 conv RGB → 31 bands after Reinhard at key 0.18 (its own pre-processing)."""

        def __init__(self, cfg):
            super().__init__()
            self.conv = torch.nn.Conv2d(3, 31, 1)
            self.wavelengths = WAVELENGTHS_31

        def forward(self, rgb):
            y = (rgb.clamp(min=0) * 0.2126).sum(1, keepdim=True)
            f = 0.18 / torch.exp(torch.log(y.clamp(min=1e-12)).mean((2, 3), keepdim=True))
            x = rgb.clamp(min=0) * f
            return torch.nn.functional.softplus(self.conv(x / (1 + x)))

    register_architecture(Architecture("unit-lin", Lin, presets={"full": {}}, learning=("similarity",),
                                       published_params=124), overwrite=True)
    try:
        assert get_architecture("unit-lin").published_params == 124
        with pytest.raises(InputError, match="unknown network architecture"):
            get_architecture("nope")
        net = Lin({})
        tf = TrainedFor(input="hdr", preprocessing=Preprocessing(), output="shape")
        path = tmp_path / "best.pt"
        with atomic_path(path) as tmp:
            torch.save({"format": CHECKPOINT_FORMAT, "arch": "unit-lin", "preset": "full",
                        "net_config": {}, "model": net.state_dict(),
                        "trained_for": tf.to_dict()}, tmp)
        m = load_model(f"mine={path}")
        assert m.name == "mine" and m.arch == "unit-lin" and trained_for(m) == tf
        rgb = np.random.default_rng(0).gamma(1, 1, (6, 5, 3)).astype(np.float32)
        assert m(rgb).shape == (6, 5, 31)
        ds = make_paired_set(tmp_path / "ds", n_scenes=3, size=8, seed=1)
        res = evaluate(ds, [m, "smits"], preprocess="both", inputs=("hdr", "ldr"), split=None)
        mine = {(s["input"], s["preprocess"], s["restore"]) for s in res.summary if s["model"] == "mine"}
        assert mine == {("hdr", "on", True), ("ldr", "on", True)}
        # a checkpoint naming an architecture nobody registered is a named error
        bad = tmp_path / "bad.pt"
        torch.save({"format": CHECKPOINT_FORMAT, "arch": "ghost", "net_config": {},
                    "model": {}}, bad)
        with pytest.raises(InputError, match="ghost"):
            load_model(str(bad))
        with atomic_path(tmp_path / "broken.pt") as tmp:
            torch.save({"format": CHECKPOINT_FORMAT, "arch": "unit-lin", "net_config": {},
                        "model": {"conv.weight": torch.zeros(1)}}, tmp)
        with pytest.raises(FormatError, match="do not fit"):
            load_model(str(tmp_path / "broken.pt"))
    finally:
        ARCHITECTURES.pop("unit-lin", None)


def test_legacy_checkpoint_declarations_are_derived(tmp_path):
    pytest.importorskip("torch")
    from mehs.ssr.contract import trained_for
    from mehs.ssr.models import load_model
    from mehs.ssr.net.model import build_network
    from mehs.ssr.net.train import TrainConfig, save_checkpoint
    from mehs.ssr.preprocess import PAPER_PREPROCESSING

    for variant, reinhard, out in (("hdrssr", True, "shape"), ("fcdensenet", False, "spectra")):
        net = build_network(variant=variant, reinhard=reinhard, **TINY)
        p = tmp_path / f"{variant}.pt"
        save_checkpoint(p, net, None, None, epoch=0, train_config=TrainConfig(), history=[],
                        extra={"input": "ldr"})
        tf = trained_for(load_model(str(p)))
        from mehs.ssr.net.train import read_checkpoint

        # the network's own record of its input wins over the training run's notes
        assert tf.output == out and tf.input == read_checkpoint(p)["net_config"].get("input", "ldr")
        assert tf.preprocessing == (PAPER_PREPROCESSING if reinhard else None)
    assert json.dumps(tf.to_dict())
