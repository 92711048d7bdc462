"""Conversion time of SSR models on one large image (the paper's Table 5).

:func:`time_models` times the conversion as scored — the model and its
luminance restoration (none for end-to-end models) — on the CPU and, when
available, on CUDA for models that can move there (torch networks).
"""

from __future__ import annotations

import re
import time
from typing import Any, Sequence

import numpy as np

from mehs.ssr.contract import trained_for
from mehs.ssr.pipeline import predict

#: Paper Table 5 (CPU i9-11900 / GPU RTX 3090, 2048×1024), by row name.
PAPER_SECONDS = {"smits": (0.788, None), "hdrssr": (16.338, 1.066), "ours": (16.338, 1.066),
                 "mikamoto": (14.766, 0.948), "galliani": (6.337, 0.946),
                 "hscnn-d": (51.998, 2.344), "hscnnd": (51.998, 2.344),
                 "awan": (324.586, 7.110)}


def synthetic_timing_image(shape: tuple[int, int], seed: int = 0) -> np.ndarray:
    """float32 ``(H, W, 3)`` linear HDR RGB of gamma-distributed 16-pixel blocks (×10):
    the image models are timed on when the dataset offers none (also the benchmarks')."""
    rng = np.random.default_rng(seed)
    h, w = shape
    base = rng.gamma(1.0, 1.0, (h // 16 + 1, w // 16 + 1, 3)).astype(np.float32)
    rgb = np.repeat(np.repeat(base, 16, 0), 16, 1)[:h, :w] * np.float32(10.0)
    return np.ascontiguousarray(rgb)


def _cuda_available() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return bool(torch.cuda.is_available())


def time_models(models: Sequence, *, shape: tuple[int, int] = (1024, 2048), repeat: int = 1,
                seed: int = 0, devices: Sequence[str] = ("cpu",),
                rgb: np.ndarray | None = None) -> list[dict[str, Any]]:
    """Conversion time of each model on one HDR image of ``shape`` (paper Table 5).

    ``models``: model objects or ``(model, name)`` pairs; ``rgb`` (optional) an
    image from the dataset, else a synthetic one. The conversion as scored (the
    model and its luminance restoration; none for end-to-end models) is warmed
    up on a 16×16 crop, then timed ``repeat`` times (best kept). On ``"cuda"``
    (when available) models offering ``on_device(device)`` (torch networks) are
    timed too (``cuda_seconds``; ``None`` otherwise). A model that runs out of
    memory gets ``seconds=None`` and the reason in ``error``.
    """
    rgb = synthetic_timing_image(shape, seed) if rgb is None else np.ascontiguousarray(rgb, dtype=np.float32)
    h, w = rgb.shape[:2]
    use_cuda = "cuda" in devices and _cuda_available()

    def clock(model) -> float:
        # the conversion as scored: the model plus its luminance restoration (none for e2e)
        restore = trained_for(model).output != "spectra"
        predict(model, rgb[:16, :16], restore=restore)
        best = np.inf
        for _ in range(max(1, repeat)):
            t0 = time.perf_counter()
            predict(model, rgb, restore=restore)
            best = min(best, time.perf_counter() - t0)
        return best

    def attempt(fn):
        """``(seconds, None)``, or ``(None, why)`` when the device runs out of memory: one
        network too large for the image must not cost the other methods their row."""
        try:
            return fn(), None
        except (MemoryError, RuntimeError) as exc:  # torch reports allocation failures so
            msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            if isinstance(exc, RuntimeError) and "memory" not in msg.lower():
                raise
            asked = re.search(r"allocate (\d+) bytes", msg)
            return None, ("out of memory" + (f" ({int(asked.group(1)) / 2**30:.3g} GiB asked)"
                                             if asked else ""))

    out = []
    for item in models:
        model, name = item if isinstance(item, tuple) else (item, getattr(item, "name", "model"))
        best, why = attempt(lambda: clock(model))
        cuda, why_cuda = None, None
        if use_cuda and callable(getattr(model, "on_device", None)):
            cuda, why_cuda = attempt(lambda: clock(model.on_device("cuda")))
        paper = PAPER_SECONDS.get(name.lower(), (None, None)) if (h, w) == (1024, 2048) else (None, None)
        out.append({"model": name, "shape": [h, w], "seconds": best, "cuda_seconds": cuda,
                    "megapixels_per_second": None if best is None else h * w / 1e6 / best,
                    "paper_seconds": paper[0], "paper_gpu_seconds": paper[1],
                    "error": why, "cuda_error": why_cuda})
    return out
