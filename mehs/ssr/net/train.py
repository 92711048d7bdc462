"""Training of the SSR networks on pseudo-HDR-RGB / HS pairs, with checkpoints and resume.

Recipe (the reference method's): Adam, learning rate by cosine annealing with
warm restarts (η_max = 0.002, η_min = 0.0001, T0 = 20 epochs, T_mult = 1,
stepped every batch with the fractional epoch), random square patches with
random horizontal/vertical flips and 0°/90°/270° rotations, deterministic under
``seed`` (the patch draw of epoch ``e`` comes from ``default_rng([seed, e])`` and
torch's dropout draws from a seed made of ``(seed, e)``, so a resumed run trains
exactly as an uninterrupted one).

An *epoch* is ``ceil(n_images · patches_per_image / batch)`` batches.

Every zoo architecture (:data:`mehs.ssr.net.zoo.ARCHITECTURES`) trains with this one
recipe, in either learning mode (the loss is the network's, :meth:`SSRNetwork.loss`);
an architecture's ``recipe`` (AWAN: η_max 2e-4, η_min 1e-5, as the paper did) changes
only the learning-rate range, and only where the caller leaves it at its default.

Checkpoints (``torch.save`` of plain dicts, written atomically; format 2 records
``arch``, ``preset``, ``mode`` and the trained input beside the weights; format 1,
the single-architecture checkpoints, still load):
``OUT/last.pt`` after every epoch, ``OUT/best.pt`` whenever the validation loss
(training loss when there is no validation set) improves; ``OUT/history.json``
holds the per-epoch figures and ``OUT/config.json`` the configuration.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from mehs import __version__
from mehs.errors import FormatError, InputError
from mehs.io.atomic import atomic_path, check_output_dir, make_output_dir, write_json_atomic
from mehs.ssr.net.base import NetConfig
from mehs.ssr.net.zoo import build_network

CHECKPOINT_FORMAT = "mehs-ssr-net/2"
#: Formats :func:`read_checkpoint` accepts (1: before the zoo; its config is migrated).
READABLE_FORMATS = ("mehs-ssr-net/1", CHECKPOINT_FORMAT)


@dataclass
class TrainingPair:
    """One training image: linear RGB ``(H, W, 3)`` float32, HS ``(H, W, B)`` float32,
    ``valid`` ``(H, W)`` bool (False = excluded from the loss), an id for messages."""

    rgb: np.ndarray
    hs: np.ndarray
    valid: np.ndarray | None = None
    id: str = ""

    def __post_init__(self):
        self.rgb = np.ascontiguousarray(self.rgb, dtype=np.float32)
        self.hs = np.ascontiguousarray(self.hs, dtype=np.float32)
        if self.rgb.ndim != 3 or self.rgb.shape[-1] != 3:
            raise InputError(f"pair {self.id!r}: RGB must be (H, W, 3), got {self.rgb.shape}")
        if self.hs.ndim != 3 or self.hs.shape[:2] != self.rgb.shape[:2]:
            raise InputError(f"pair {self.id!r}: HS {self.hs.shape} does not match RGB "
                             f"{self.rgb.shape}")
        if self.valid is None:
            self.valid = np.ones(self.rgb.shape[:2], dtype=bool)
        self.valid = np.asarray(self.valid, dtype=bool)
        if self.valid.shape != self.rgb.shape[:2]:
            raise InputError(f"pair {self.id!r}: mask {self.valid.shape} does not match "
                             f"image {self.rgb.shape[:2]}")
        finite = np.isfinite(self.rgb).all(-1) & np.isfinite(self.hs).all(-1)
        if not finite.all():
            # NaN must never reach the loss: such pixels are zeroed and masked out.
            self.rgb[~finite] = 0
            self.hs[~finite] = 0
            self.valid = self.valid & finite


@dataclass
class TrainConfig:
    """Training hyper-parameters (stored in every checkpoint)."""

    epochs: int = 40
    batch: int = 8
    patch: int = 64
    patches_per_image: int = 16
    lr_max: float = 0.002
    lr_min: float = 0.0001
    T0: int = 20
    T_mult: int = 1
    seed: int = 0
    augment: bool = True
    device: str = "cpu"
    #: ``"mse"`` or ``"mrae"`` (:data:`mehs.ssr.net.base.LOSSES`). The paper names MSE only
    #: for its end-to-end runs ("we changed the loss function to mean squared error",
    #: §4.1), not its similarity-mode loss; MST++ and the NTIRE entries train on MRAE.
    loss: str = "mse"

    def __post_init__(self):
        # torch raises a bare ValueError for a negative learning rate only once
        # training starts; check every field where the user's values arrive
        for name in ("epochs", "batch", "patch", "patches_per_image", "T0", "T_mult"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be at least 1, got {getattr(self, name)}")
        from mehs.ssr.net.base import LOSSES

        if self.loss not in LOSSES:
            raise InputError(f"loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if not (math.isfinite(self.lr_max) and self.lr_max > 0):
            raise InputError(f"lr_max must be a positive number, got {self.lr_max}")
        if not (math.isfinite(self.lr_min) and 0 <= self.lr_min <= self.lr_max):
            raise InputError(f"lr_min must be between 0 and lr_max ({self.lr_max}), "
                             f"got {self.lr_min}")

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "TrainConfig":
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    @classmethod
    def for_arch(cls, arch: str, **overrides) -> "TrainConfig":
        """The recipe with the architecture's changes (AWAN's learning-rate range) applied;
        ``overrides`` win over both."""
        from mehs.ssr.net.zoo import get_architecture

        return cls(**{**get_architecture(arch).recipe, **overrides})


@dataclass
class TrainResult:
    """What :func:`train_network` returns."""

    network: torch.nn.Module
    history: list[dict[str, float]] = field(default_factory=list)
    last_checkpoint: Path | None = None
    best_checkpoint: Path | None = None


def resolve_device(device: str) -> torch.device:
    """``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"`` → a torch device, or :class:`InputError`."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise InputError(f"unknown torch device {device!r} ({exc})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise InputError(f"device {device!r} requested but CUDA is not available "
                         f"(torch {torch.__version__})")
    if dev.type == "mps" and not torch.backends.mps.is_available():
        raise InputError(f"device {device!r} requested but MPS is not available")
    return dev


def augment_patch(rgb: np.ndarray, hs: np.ndarray, valid: np.ndarray,
                  rng: np.random.Generator):
    """Random horizontal/vertical flip and a rotation by 0°, 90° or 270° of ``(p, p, C)`` patches."""
    k = int(rng.choice([0, 1, 3]))
    flip_h, flip_v = rng.random(2) < 0.5
    out = []
    for a in (rgb, hs, valid):
        if flip_h:
            a = a[:, ::-1]
        if flip_v:
            a = a[::-1]
        out.append(np.rot90(a, k, axes=(0, 1)))
    return out


def epoch_torch_seed(seed: int, epoch: int) -> int:
    """The torch seed of epoch ``epoch`` (dropout draws), a function of ``(seed, epoch)`` only."""
    return int(np.random.SeedSequence([int(seed), int(epoch), 1]).generate_state(1)[0])


def sample_batch(pairs: Sequence[TrainingPair], batch: int, patch: int,
                 rng: np.random.Generator, augment: bool = True):
    """Draw ``batch`` random ``patch``×``patch`` crops → tensors ``(N,3,p,p)``, ``(N,B,p,p)``,
    ``(N,1,p,p)`` bool."""
    rgbs, hss, valids = [], [], []
    for idx in rng.integers(0, len(pairs), size=batch):
        pr = pairs[int(idx)]
        h, w = pr.rgb.shape[:2]
        y = int(rng.integers(0, h - patch + 1))
        x = int(rng.integers(0, w - patch + 1))
        sl = (slice(y, y + patch), slice(x, x + patch))
        r, s, v = pr.rgb[sl], pr.hs[sl], pr.valid[sl]
        if augment:
            r, s, v = augment_patch(r, s, v, rng)
        rgbs.append(r)
        hss.append(s)
        valids.append(v)

    def to_t(arrs):
        return torch.from_numpy(np.ascontiguousarray(np.stack(arrs).transpose(0, 3, 1, 2)))

    return (to_t(rgbs), to_t(hss),
            torch.from_numpy(np.ascontiguousarray(np.stack(valids)[:, None])))


def _image_tensors(pr: TrainingPair, device):
    return (torch.from_numpy(pr.rgb.transpose(2, 0, 1)[None].copy()).to(device),
            torch.from_numpy(pr.hs.transpose(2, 0, 1)[None].copy()).to(device),
            torch.from_numpy(pr.valid[None, None].copy()).to(device))


@torch.no_grad()
def evaluate_pairs(network, pairs: Sequence[TrainingPair], device="cpu",
                   loss: str = "mse") -> dict[str, float]:
    """Mean loss, SAM (degrees) and MRAE over whole images: the paper's two metrics
    (§3.6.3), of the luminance-restored spectra, per image as :mod:`mehs.ssr.metrics`
    defines them (SAM: zero-norm pixels excluded; MRAE: elements with ``y ≤ 0`` excluded)."""
    network.eval()
    losses, sams, mraes = [], [], []
    for pr in pairs:
        rgb, hs, valid = _image_tensors(pr, device)
        pred = network(rgb)
        losses.append(float(network.loss(pred, hs, valid, loss)))
        spec = network.restore_luminance(pred, rgb) if network.predicts_standard_spectrum else pred
        num = (spec * hs).sum(1)
        den = spec.norm(dim=1) * hs.norm(dim=1)
        ok = (den > 0) & valid[:, 0]
        cos = torch.clamp(num[ok] / den[ok], -1.0, 1.0)
        if cos.numel():
            sams.append(float(torch.rad2deg(torch.arccos(cos)).mean()))
        pos = (hs > 0) & valid
        if bool(pos.any()):
            mraes.append(float(((spec - hs).abs()[pos] / hs[pos]).mean()))
    return {"loss": float(np.mean(losses)) if losses else math.nan,
            "sam_deg": float(np.mean(sams)) if sams else math.nan,
            "mrae": float(np.mean(mraes)) if mraes else math.nan}


def save_checkpoint(path: str | Path, network, optimizer, scheduler, *, epoch: int,
                    train_config: TrainConfig, history: list, extra: dict | None = None) -> Path:
    """Write a checkpoint atomically (temp file + rename)."""
    state = {
        "format": CHECKPOINT_FORMAT,
        "software_version": __version__,
        "variant": network.config.variant,
        "arch": network.config.arch,
        "preset": network.config.preset,
        "mode": network.config.mode,
        "trained_input": network.trained_input(),
        "net_config": network.config.to_dict(),
        "train_config": asdict(train_config),
        "epoch": int(epoch),
        "model": network.state_dict(),
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "scheduler": scheduler.state_dict() if scheduler is not None else None,
        "history": list(history),
        "extra": dict(extra or {}),
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return Path(path)


def read_checkpoint(path: str | Path, map_location="cpu") -> dict:
    """Load a checkpoint dict (``weights_only``: no code is unpickled), checking its format."""
    path = Path(path)
    if not path.is_file():
        raise InputError("checkpoint not found", path)
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # torch raises several unrelated types for corrupt files
        raise FormatError(f"not a readable torch checkpoint ({type(exc).__name__}: {exc})",
                          path) from None
    if not isinstance(state, dict) or state.get("format") not in READABLE_FORMATS:
        raise FormatError(f"not a mehs SSR network checkpoint (expected format "
                          f"{CHECKPOINT_FORMAT!r})", path)
    try:
        NetConfig.from_dict(state["net_config"])
    except (InputError, KeyError, TypeError) as exc:
        raise FormatError(f"checkpoint has no usable network configuration ({exc})",
                          path) from None
    return state


def load_network(path: str | Path, map_location="cpu"):
    """Rebuild the network stored in a checkpoint, in eval mode. Returns ``(network, state)``."""
    state = read_checkpoint(path, map_location)
    try:
        net = build_network(NetConfig.from_dict(state["net_config"]))
    except InputError as exc:
        raise FormatError(f"checkpoint configuration does not build ({exc})", path) from None
    try:
        net.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise FormatError(f"checkpoint weights do not fit its own configuration ({exc})",
                          path) from None
    net.eval()
    return net, state


def _check_same_scenes(state: dict, pairs: Sequence[TrainingPair], last: Path) -> None:
    """A resumed run must train on the scenes its checkpoint recorded (``extra.train_ids``):
    other data (another dataset, split or hold-out seed) would continue a schedule and a
    history that belong to a different training set, silently."""
    was = (state.get("extra") or {}).get("train_ids")
    if was is None:
        return       # a checkpoint from before the ids were recorded
    was, now = set(map(str, was)), {str(p.id) for p in pairs}
    if was != now:
        raise InputError(f"the checkpoint was trained on other scenes ({len(now - was)} new, "
                         f"{len(was - now)} missing, e.g. {sorted(now ^ was)[:3]}); resume with "
                         "the same dataset, split and --seed, or train into another folder",
                         last)


def train_network(pairs: Sequence[TrainingPair], out_dir: str | Path, *,
                  net_config: NetConfig | None = None,
                  train_config: TrainConfig | None = None,
                  val_pairs: Sequence[TrainingPair] = (), resume: bool = False,
                  progress: bool = True, extra: dict | None = None) -> TrainResult:
    """Train a network and write checkpoints to ``out_dir``.

    Parameters
    ----------
    pairs, val_pairs
        Training and validation images (:class:`TrainingPair`; HS bands must
        match ``net_config.wavelengths``).
    out_dir
        Checkpoint folder. If it already holds ``last.pt``, ``resume=True``
        continues from it (its stored configurations win over the arguments,
        except ``epochs`` and ``device``); ``resume=False`` is an error then, so
        a finished run is never overwritten by accident.
    extra
        JSON-able provenance stored in the checkpoints (e.g. the dataset path).
    """
    out_dir = check_output_dir(out_dir)
    net_config = net_config or NetConfig()
    # (the architecture's recipe, as the CLI uses: AWAN trains at its paper's 2e-4 range)
    tc = train_config or TrainConfig.for_arch(net_config.arch)
    last = out_dir / "last.pt"
    state = None
    if last.exists():
        if not resume:
            raise InputError("already holds a checkpoint (last.pt); pass resume=True "
                             "(--resume) to continue it or choose another output folder",
                             out_dir)
        state = read_checkpoint(last)
        _check_same_scenes(state, pairs, last)
        net_config = NetConfig.from_dict(state["net_config"])
        tc = TrainConfig.from_dict({**state["train_config"], "epochs": tc.epochs,
                                    "device": tc.device})
    if not pairs:
        raise InputError("no training pairs")
    n_bands = len(net_config.wavelengths)
    for pr in list(pairs) + list(val_pairs):
        if pr.hs.shape[-1] != n_bands:
            raise InputError(f"pair {pr.id!r} has {pr.hs.shape[-1]} bands, the network "
                             f"predicts {n_bands}")
    min_side = min(min(pr.rgb.shape[:2]) for pr in pairs)
    patch = min(tc.patch, min_side)
    device = resolve_device(tc.device)

    torch.manual_seed(tc.seed)
    network = build_network(net_config).to(device)
    optimizer = torch.optim.Adam(network.parameters(), lr=tc.lr_max)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingWarmRestarts(
        optimizer, T_0=tc.T0, T_mult=tc.T_mult, eta_min=tc.lr_min)
    history: list[dict[str, float]] = []
    start_epoch = 0
    if state is not None:
        network.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        history = list(state["history"])
        start_epoch = int(state["epoch"]) + 1

    ids = [str(getattr(p, "id", "") or "") for p in pairs]
    extra = dict(extra or {})
    if all(ids) and len(set(ids)) == len(ids):
        extra.setdefault("train_ids", ids)     # what a resumed run is checked against
    make_output_dir(out_dir)
    write_json_atomic(out_dir / "config.json", {
        "format": CHECKPOINT_FORMAT, "software_version": __version__,
        "net_config": network.config.to_dict(), "train_config": asdict(tc),
        "n_train": len(pairs), "n_val": len(val_pairs), "extra": extra or {}})
    best_key = "val_loss" if val_pairs else "train_loss"
    best = min((h[best_key] for h in history if best_key in h), default=math.inf)
    n_batches = max(1, math.ceil(len(pairs) * tc.patches_per_image / tc.batch))
    result = TrainResult(network=network, history=history)

    from tqdm.auto import tqdm

    bar = tqdm(range(start_epoch, tc.epochs), desc=f"train {net_config.variant}",
               unit="epoch", disable=not progress, initial=start_epoch, total=tc.epochs)
    for epoch in bar:
        network.train()
        rng = np.random.default_rng([tc.seed, epoch])
        # torch's own draws (dropout) also restart per epoch from (seed, epoch): a resumed run
        # then trains exactly as an uninterrupted one (the generator state is not in last.pt)
        torch.manual_seed(epoch_torch_seed(tc.seed, epoch))
        t0 = time.perf_counter()
        total = 0.0
        for i in range(n_batches):
            rgb, hs, valid = (t.to(device) for t in
                              sample_batch(pairs, tc.batch, patch, rng, tc.augment))
            optimizer.zero_grad(set_to_none=True)
            loss = network.loss(network(rgb), hs, valid, tc.loss)
            if not torch.isfinite(loss):
                raise InputError(f"training diverged at epoch {epoch} (loss {float(loss)}); "
                                 "check the data or lower the learning rate")
            loss.backward()
            optimizer.step()
            scheduler.step(epoch + (i + 1) / n_batches)
            total += float(loss.detach())
        entry = {"epoch": epoch, "train_loss": total / n_batches,
                 "lr": optimizer.param_groups[0]["lr"],
                 "seconds": time.perf_counter() - t0}
        if val_pairs:
            v = evaluate_pairs(network, val_pairs, device, tc.loss)
            entry["val_loss"], entry["val_sam_deg"] = v["loss"], v["sam_deg"]
            entry["val_mrae"] = v["mrae"]
        history.append(entry)
        bar.set_postfix({k: f"{entry[k]:.4g}" for k in ("train_loss", "val_loss") if k in entry})
        # best.pt before last.pt: a run killed between the two writes resumes from the
        # previous last.pt and redoes this epoch. The other order left a last.pt whose
        # history names this epoch the best while best.pt still held an older one, and
        # the resumed run never replaced it (its `best` already counted this epoch).
        if entry[best_key] < best:
            best = entry[best_key]
            result.best_checkpoint = save_checkpoint(
                out_dir / "best.pt", network, None, None, epoch=epoch, train_config=tc,
                history=history, extra=extra)
        result.last_checkpoint = save_checkpoint(
            last, network, optimizer, scheduler, epoch=epoch, train_config=tc,
            history=history, extra=extra)
        write_json_atomic(out_dir / "history.json", history)
    network.eval()
    if result.last_checkpoint is None and last.exists():
        result.last_checkpoint = last
    if result.best_checkpoint is None and (out_dir / "best.pt").exists():
        result.best_checkpoint = out_dir / "best.pt"
    return result


def history_summary(history: list[dict[str, float]]) -> str:
    """One line: first and last training loss (and validation figures when present)."""
    if not history:
        return "no epochs run"
    a, b = history[0], history[-1]
    s = f"epochs {a['epoch']}..{b['epoch']}: train loss {a['train_loss']:.4g} → {b['train_loss']:.4g}"
    if "val_loss" in b:
        s += f"; val loss {b['val_loss']:.4g}, val SAM {b['val_sam_deg']:.3f}°"
        if "val_mrae" in b:
            s += f", val MRAE {b['val_mrae']:.4f}"
    return s


