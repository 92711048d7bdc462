"""Registers the networks with the SSR model registry (imported by :mod:`mehs.ssr.models`).

- ``hdrssr``: the HDR SSR network (learns spectral similarity; luminance restored);
- ``fcdensenet``: the plain end-to-end FC-DenseNet.

Both need a trained checkpoint: ``load_model("hdrssr", checkpoint="runs/x/best.pt")``;
a checkpoint file (``.pt``) or an exported ``.onnx`` can also be named directly.
"""

from __future__ import annotations

from mehs.errors import InputError
from mehs.ssr.models import register_model


def _factory(variant: str):
    def make(checkpoint=None, path=None, name=None, device: str = "cpu"):
        from mehs.ssr.net.export import load_torch_model

        ckpt = checkpoint or path
        if ckpt is None:
            raise InputError(f"model {variant!r} needs a trained checkpoint: "
                             f"load_model({variant!r}, checkpoint='OUT/best.pt') "
                             f"(train one with `mehs train-ssr DATASET --variant {variant}`)")
        model = load_torch_model(ckpt, name=name, device=device)
        if model.network.config.variant != variant:
            raise InputError(f"holds a {model.network.config.variant!r} network, not "
                             f"{variant!r}", ckpt)
        return model

    make.__name__ = f"make_{variant}"
    return make


register_model("hdrssr", _factory("hdrssr"),
               description="HDR SSR network: FC-DenseNet + channel attention + sigmoid/"
                           "Mexican-hat basis branches, learns spectral similarity "
                           "(torch; needs checkpoint=)", overwrite=True)
register_model("fcdensenet", _factory("fcdensenet"),
               description="plain FC-DenseNet end to end, MSE on spectra "
                           "(torch; needs checkpoint=)", overwrite=True)
