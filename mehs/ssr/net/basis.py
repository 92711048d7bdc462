"""Spectral basis functions and the per-pixel basis branches of the HDR SSR network.

Each branch is a 1×1 convolution that predicts, per pixel, ``n`` weights
``w_i`` and the parameters of ``n`` basis functions ``f_i``, and evaluates
``F(λ) = Σ_i w_i f_i(λ)`` at the output wavelengths.

Wavelength normalisation: basis functions are evaluated on
``λn = (λ − 400 nm) / (700 nm − 400 nm)``, i.e. the 31 output bands 400…700 nm
map to ``0, 1/30, …, 1``. This keeps the polynomial coefficients of the sigmoid
basis and the centres/widths of the Mexican hats of order one, so a freshly
initialised 1×1 convolution already produces smooth, non-degenerate spectra.

References
----------
- Jakob, W., Hanika, J. (2019). A low-dimensional function space for efficient
  spectral upsampling. Computer Graphics Forum 38(2).
- Ricker, N. (1953). The form and laws of propagation of seismic wavelets
  (the "Mexican hat" wavelet family).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
import torch.nn.functional as F

from mehs.ssr.net.pooling import compiling, plain_graph_wanted

#: Wavelength range mapped to [0, 1] before the basis functions are evaluated.
LAMBDA_RANGE_NM = (400.0, 700.0)

#: Smallest Mexican-hat width (in normalised λ) — keeps 1/√a finite.
MIN_HAT_WIDTH = 0.02


def normalise_wavelengths(wavelengths, lo: float = LAMBDA_RANGE_NM[0],
                          hi: float = LAMBDA_RANGE_NM[1]) -> np.ndarray:
    """Map wavelengths in nm to ``(λ − lo) / (hi − lo)`` (400…700 nm → 0…1), float64 ``(B,)``."""
    wl = np.asarray(wavelengths, dtype=np.float64).reshape(-1)
    return (wl - lo) / (hi - lo)


def sigmoid_Jakob2019(x: torch.Tensor) -> torch.Tensor:
    """The algebraic sigmoid ``S(x) = ½ + x / (2 √(1 + x²))`` of Jakob & Hanika 2019."""
    return 0.5 + x / (2.0 * torch.sqrt(1.0 + x * x))


def sigmoid_basis(lam: torch.Tensor, c0: torch.Tensor, c1: torch.Tensor,
                  c2: torch.Tensor) -> torch.Tensor:
    """Sigmoid-polynomial basis ``f(λ) = S(c0 λ² + c1 λ + c2)``.

    All arguments broadcast together (e.g. ``lam`` of shape ``(L, 1, 1)`` with
    coefficients of shape ``(N, 1, H, W)`` give ``(N, L, H, W)``).
    """
    return sigmoid_Jakob2019((c0 * lam + c1) * lam + c2)


def mexican_hat_basis(lam: torch.Tensor, a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Mexican-hat basis ``f(λ) = (1/√a) (1 − 2u²) exp(−u²)`` with ``u = (λ − c)/a``.

    ``a`` (width) must be positive; arguments broadcast together.
    """
    u2 = ((lam - c) / a) ** 2
    return (1.0 - 2.0 * u2) * torch.exp(-u2) / torch.sqrt(a)


#: Basis families by name (the basis functions themselves, author+year where there is one).
BASIS_FUNCTIONS = {"sigmoid_Jakob2019": sigmoid_basis, "mexican_hat": mexican_hat_basis}


class _BasisBranch(nn.Module):
    """1×1 conv → per-pixel weights and basis parameters → ``F(λ)`` on the output bands.

    Input ``(N, C, H, W)`` features; output ``(N, L, H, W)`` with ``L`` = number
    of wavelengths. The sum over the ``n`` basis functions is accumulated one
    function at a time, so memory stays ``O(N·L·H·W)`` (a full-HD image would
    otherwise need ``n`` times that). The branch is per pixel, so it is
    evaluated in strips of rows of about ``chunk_pixels`` pixels whose
    temporaries stay in cache: the result is the same (up to float32 rounding of
    the 1×1 convolution) and a 2-Mpixel image is
    about 10× faster on a CPU than in one piece. Strips are skipped while
    tracing (ONNX export), where the graph must keep H and W dynamic, and when
    gradients are needed (autograd keeps every strip's temporaries anyway).
    """

    n_params: int = 0
    chunk_pixels: int = 32768

    def __init__(self, in_channels: int, wavelengths, n_basis: int = 10):
        super().__init__()
        self.n_basis = int(n_basis)
        self.head = nn.Conv2d(in_channels, self.n_basis * (1 + self.n_params), kernel_size=1)
        lam = torch.as_tensor(normalise_wavelengths(wavelengths), dtype=torch.float32)
        self.register_buffer("lam", lam.view(1, -1, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
        """``(N, C, H, W)`` features → ``(N, L, H, W)``; into ``out`` (that shape) if given."""
        n, _, h, w = x.shape
        # (a compiler first: dynamo folds its test, and would break its graph at the
        # ContextVar read and unroll the strips for one image size)
        if (self.chunk_pixels <= 0 or compiling()
                or (torch.is_grad_enabled() and x.requires_grad)
                or plain_graph_wanted() or torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()):
            # training: autograd keeps every strip's temporaries anyway, strips only add work
            y = self._evaluate(x)
            return y if out is None else out.copy_(y)
        rows = max(1, self.chunk_pixels // max(1, n * w))
        if rows >= h and out is None:
            return self._evaluate(x)
        # each strip lands in the output: no list of strips and their concatenation
        # (two image-sized copies of the branch) held at once
        if out is None:
            out = x.new_empty(n, self.lam.shape[1], h, w)
        for r in range(0, h, rows):
            out[:, :, r:r + rows] = self._evaluate(x[:, :, r:r + rows])
        return out

    def _evaluate(self, x: torch.Tensor) -> torch.Tensor:  # pragma: no cover
        raise NotImplementedError


class SigmoidBasisBranch(_BasisBranch):
    """Branch (a): ``n`` sigmoid-polynomial basis functions (raw coefficients c0, c1, c2).

    Evaluated as ``Σ w_i/2 + Σ (w_i/2) · x_i / √(1 + x_i²)`` with fused
    multiply-adds — the same numbers as :func:`sigmoid_basis`, half the
    full-size tensor operations (this branch dominates the training time).
    """

    n_params = 3

    def _evaluate(self, x: torch.Tensor) -> torch.Tensor:
        p = self.head(x)
        n = self.n_basis
        half_w = 0.5 * p[:, :n]
        c0, c1, c2 = p[:, n:2 * n], p[:, 2 * n:3 * n], p[:, 3 * n:4 * n]
        lam = self.lam
        out = half_w.sum(dim=1, keepdim=True)
        for i in range(n):
            sl = slice(i, i + 1)
            t = torch.addcmul(c2[:, sl], torch.addcmul(c1[:, sl], c0[:, sl], lam), lam)
            t = t * torch.rsqrt(torch.addcmul(torch.ones_like(t), t, t))
            out = torch.addcmul(out, half_w[:, sl], t)
        return out


class MexicanHatBranch(_BasisBranch):
    """Branch (b): ``n`` Mexican hats; centre ``c = sigmoid(raw)`` ∈ (0, 1) (the normalised
    band range), width ``a = 0.02 + softplus(raw)`` so that ``1/√a`` stays bounded.

    Evaluated with ``u = λ/a − c/a``, ``e = exp(−u²)``, ``f = e − 2u²e`` and the
    weight folded with ``1/√a`` — the same numbers as :func:`mexican_hat_basis`.
    """

    n_params = 2

    def _evaluate(self, x: torch.Tensor) -> torch.Tensor:
        p = self.head(x)
        n = self.n_basis
        w = p[:, :n]
        a = MIN_HAT_WIDTH + F.softplus(p[:, n:2 * n])
        c = torch.sigmoid(p[:, 2 * n:3 * n])
        inv_a = 1.0 / a
        w_scaled = w * torch.sqrt(inv_a)
        shift = -c * inv_a
        lam = self.lam
        out = None
        for i in range(n):
            sl = slice(i, i + 1)
            u2 = torch.addcmul(shift[:, sl], lam, inv_a[:, sl]).square()
            e = torch.exp(-u2)
            f = torch.addcmul(e, u2, e, value=-2.0)
            out = w_scaled[:, sl] * f if out is None else torch.addcmul(out, w_scaled[:, sl], f)
        return out
