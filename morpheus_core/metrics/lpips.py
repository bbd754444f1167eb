"""LPIPS (Zhang et al. 2018, v0.1) implemented natively in PyTorch, weights from one safetensors file.

The network is the one of the reference implementation (``richzhang/PerceptualSimilarity``,
``lpips.LPIPS(net='alex' | 'vgg', version='0.1')``):

1. inputs in [0, 1] are mapped to [-1, 1] (``normalize=True`` there), then shifted and scaled by
   the ScalingLayer constants (shift −0.030, −0.088, −0.188; scale 0.458, 0.448, 0.450);
2. a torchvision AlexNet or VGG16 ``features`` trunk, tapped after its ReLUs (AlexNet relu1..5,
   VGG16 relu1_2, relu2_2, relu3_3, relu4_3, relu5_3);
3. each tap's features are unit-normalised over channels (``x / (‖x‖₂ + 1e-10)``), the squared
   difference goes through a learned 1×1 convolution to one channel (no bias), is averaged over
   space, and the layers are summed.

The dropout in front of each 1×1 head only acts in training and is left out.

Weights file (``lpips.safetensors``), keys = this module's ``state_dict``:

- ``features.<i>.weight`` / ``features.<i>.bias``: the trunk convolutions with torchvision's
  indices (AlexNet 0, 3, 6, 8, 10; VGG16 0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28);
- ``lin.<k>.weight`` (1×C_k×1×1), k = 0..4: the LPIPS heads (``lin<k>.model.1.weight`` upstream);
- metadata ``net`` = ``alex`` | ``vgg16`` (optional: the convolution indices identify the trunk).

The trunk follows from the key indices and the channel counts and kernel sizes from the tensors,
so a file with narrower layers (the tests' stand-ins) loads through the same code; strides and
paddings are the architecture's. ``convert_lpips_checkpoint`` (or ``python -m morpheus_core.metrics.lpips
--trunk alexnet-owt-7be5be79.pth --lin alex.pth --out lpips.safetensors``) writes the file from
the official torchvision trunk weights and the LPIPS v0.1 head weights; it needs no torchvision.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

LPIPS_FILE = "lpips.safetensors"
FORMAT = "morpheus3d-lpips"
# The ScalingLayer of LPIPS v0.1: ImageNet statistics expressed for inputs in [-1, 1].
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10


@dataclass(frozen=True)
class Conv:
    kernel: int
    stride: int
    padding: int


@dataclass(frozen=True)
class Pool:
    kernel: int = 2
    stride: int = 2


RELU = "relu"
Op = Conv | Pool | str


@dataclass(frozen=True)
class Trunk:
    """A torchvision ``features`` stack up to its last tapped ReLU, in torchvision's indexing."""

    name: str
    ops: tuple[Op, ...]
    taps: tuple[int, ...]  # indices of the ReLUs whose outputs feed the heads
    channels: tuple[int, ...]  # output channels of each convolution at full size

    @property
    def conv_indices(self) -> tuple[int, ...]:
        return tuple(i for i, op in enumerate(self.ops) if isinstance(op, Conv))


def _vgg16_ops() -> tuple[Op, ...]:
    ops: list[Op] = []
    for block, n in enumerate((2, 2, 3, 3, 3)):
        if block:
            ops.append(Pool())
        ops += [Conv(3, 1, 1), RELU] * n
    return tuple(ops)


TRUNKS: Mapping[str, Trunk] = {
    "alex": Trunk(
        "alex",
        (Conv(11, 4, 2), RELU, Pool(3, 2), Conv(5, 1, 2), RELU, Pool(3, 2),
         Conv(3, 1, 1), RELU, Conv(3, 1, 1), RELU, Conv(3, 1, 1), RELU),
        (1, 4, 7, 9, 11),
        (64, 192, 384, 256, 256),
    ),
    "vgg16": Trunk("vgg16", _vgg16_ops(), (3, 8, 15, 22, 29),
                   (64, 64, 128, 128, 256, 256, 256, 512, 512, 512, 512, 512, 512)),
}
_ALIASES = {"alexnet": "alex", "vgg": "vgg16"}


class LPIPSWeightsError(ValueError):
    """An LPIPS weights file that cannot be read or does not hold the expected layout; names the file."""


def trunk_named(name: str) -> Trunk:
    key = _ALIASES.get(name, name)
    if key not in TRUNKS:
        raise ValueError(f"unknown LPIPS trunk {name!r}; known: {sorted(TRUNKS)}")
    return TRUNKS[key]


class LPIPS(nn.Module):
    """LPIPS distance between image batches in [0, 1]; lower = perceptually closer, 0 for identical."""

    def __init__(self, net: str = "alex", channels: Sequence[int] | None = None) -> None:
        super().__init__()
        self.trunk = trunk_named(net)
        channels = tuple(channels) if channels is not None else self.trunk.channels
        if len(channels) != len(self.trunk.conv_indices):
            raise ValueError(f"{self.trunk.name} has {len(self.trunk.conv_indices)} convolutions, got "
                             f"{len(channels)} channel counts")
        layers: list[nn.Module] = []
        tap_channels: list[int] = []
        c_in, conv_out = 3, iter(channels)
        for i, op in enumerate(self.trunk.ops):
            if isinstance(op, Conv):
                c = next(conv_out)
                layers.append(nn.Conv2d(c_in, c, op.kernel, op.stride, op.padding))
                c_in = c
            elif isinstance(op, Pool):
                layers.append(nn.MaxPool2d(op.kernel, op.stride))
            else:
                layers.append(nn.ReLU())
            if i in self.trunk.taps:
                tap_channels.append(c_in)
        self.features = nn.Sequential(*layers)
        self.lin = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in tap_channels)
        # Constants, not weights: kept out of the state dict so the file holds learned tensors only.
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        self.eval()

    def tap_features(self, x: Tensor) -> list[Tensor]:
        """The trunk's tapped ReLU outputs for ScalingLayer-normalised input."""
        taps: list[Tensor] = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.trunk.taps:
                taps.append(x)
        return taps

    def forward(self, x0: Tensor, x1: Tensor) -> Tensor:
        """Per-pair distance (shape N) of N×3×H×W images in [0, 1]."""
        if x0.shape != x1.shape or x0.dim() != 4 or x0.shape[1] != 3:
            raise ValueError(f"LPIPS needs two N×3×H×W batches of one shape, got {tuple(x0.shape)}, {tuple(x1.shape)}")
        n = x0.shape[0]
        x = torch.cat([x0, x1]).to(self.shift.dtype) * 2.0 - 1.0  # [0, 1] → [-1, 1], as normalize=True upstream
        # One trunk pass for both sides: the same shapes, and per-row results do not depend on the partner.
        feats = self.tap_features((x - self.shift) / self.scale)
        total = x.new_zeros(n)
        for lin, f in zip(self.lin, feats, strict=True):
            f = f / (f.pow(2).sum(dim=1, keepdim=True).sqrt() + EPS)
            total = total + lin((f[:n] - f[n:]).pow(2)).mean(dim=(1, 2, 3))
        return total

    # -- weights --------------------------------------------------------------------------------

    @classmethod
    def from_state_dict(cls, state: Mapping[str, Tensor], net: str | None = None, source: str = "state dict") -> LPIPS:
        """Build the network the tensors describe (trunk from the key indices, widths and kernel
        sizes from the shapes) and load them strictly; ``LPIPSWeightsError`` names ``source``."""
        convs = sorted({int(k.split(".")[1]) for k in state if k.startswith("features.") and k.endswith(".weight")})
        if net is None:
            matches = [t for t in TRUNKS.values() if t.conv_indices == tuple(convs)]
            if not matches:
                known = ", ".join(f"{t.name} {t.conv_indices}" for t in TRUNKS.values())
                raise LPIPSWeightsError(f"{source}: trunk convolutions at features indices {convs} match none of "
                                        f"{known}")
            trunk = matches[0]
        else:
            trunk = trunk_named(net)
            if tuple(convs) != trunk.conv_indices:
                raise LPIPSWeightsError(f"{source}: declared trunk {trunk.name} has convolutions at "
                                        f"{trunk.conv_indices}, the file at {convs}")
        channels = []
        for i in trunk.conv_indices:
            w = state[f"features.{i}.weight"]
            op = trunk.ops[i]
            assert isinstance(op, Conv)
            if w.dim() != 4 or tuple(w.shape[2:]) != (op.kernel, op.kernel):
                raise LPIPSWeightsError(f"{source}: features.{i}.weight has shape {tuple(w.shape)}, expected "
                                        f"C_out×C_in×{op.kernel}×{op.kernel} ({trunk.name})")
            channels.append(int(w.shape[0]))
        model = cls(trunk.name, channels)
        try:
            model.load_state_dict({k: v.float() for k, v in state.items()}, strict=True)
        except RuntimeError as exc:  # missing/unexpected keys or shape mismatches
            raise LPIPSWeightsError(f"{source}: not an LPIPS {trunk.name} layout: {exc}") from exc
        return model

    @classmethod
    def from_file(cls, path: Path) -> LPIPS:
        """Load ``lpips.safetensors``; an unreadable or mis-shaped file raises ``LPIPSWeightsError``."""
        from safetensors import safe_open

        path = Path(path)
        try:
            with safe_open(str(path), framework="pt") as f:
                meta = f.metadata() or {}
                state = {k: f.get_tensor(k) for k in f.keys()}
        except Exception as exc:  # safetensors raises its own error types for truncated/corrupt headers
            raise LPIPSWeightsError(f"{path}: cannot read safetensors: {exc}") from exc
        return cls.from_state_dict(state, meta.get("net"), source=str(path))

    def save(self, path: Path) -> Path:
        """Write this network in the documented layout (the tests' stand-ins use it)."""
        from safetensors.torch import save_file

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tensors = {k: v.detach().float().contiguous().cpu() for k, v in self.state_dict().items()}
        save_file(tensors, str(path), metadata={"format": FORMAT, "net": self.trunk.name, "lpips_version": "0.1"})
        return path


def _load_pth(path: Path) -> dict[str, Tensor]:
    state = torch.load(Path(path), map_location="cpu", weights_only=True)
    if isinstance(state, Mapping) and "state_dict" in state and isinstance(state["state_dict"], Mapping):
        state = state["state_dict"]
    if not isinstance(state, Mapping):
        raise LPIPSWeightsError(f"{path}: expected a state dict, got {type(state).__name__}")
    # Checkpoints saved from DataParallel carry a "module." prefix.
    return {k.removeprefix("module."): v for k, v in state.items() if isinstance(v, Tensor)}


def convert_lpips_checkpoint(src_trunk_pth: Path, src_lin_pth: Path, out: Path, net: str | None = None) -> Path:
    """Write ``out`` (``lpips.safetensors``) from the official checkpoints, without torchvision.

    - ``src_trunk_pth``: torchvision's ImageNet weights, ``alexnet-owt-7be5be79.pth`` (AlexNet) or
      ``vgg16-397923af.pth`` (VGG16) — ``features.*`` keys are kept, the classifier dropped;
    - ``src_lin_pth``: LPIPS v0.1 heads, ``lpips/weights/v0.1/alex.pth`` or ``vgg.pth`` of
      richzhang/PerceptualSimilarity (also shipped in the ``lpips`` pip package), keys
      ``lin<k>.model.1.weight`` (``lin<k>.model.0.weight`` when saved without dropout).

    The result is loaded back through ``LPIPS.from_state_dict`` before it is written, so a
    mismatched pair of files fails here with ``LPIPSWeightsError`` rather than at QA time.
    """
    trunk_state = _load_pth(src_trunk_pth)
    lin_state = _load_pth(src_lin_pth)
    state = {k: v for k, v in trunk_state.items() if k.startswith("features.")}
    if not state:
        raise LPIPSWeightsError(f"{src_trunk_pth}: no features.* tensors (expected a torchvision AlexNet/VGG16 "
                                "state dict)")
    for k in range(5):
        for sub in (1, 0):
            key = f"lin{k}.model.{sub}.weight"
            if key in lin_state:
                state[f"lin.{k}.weight"] = lin_state[key]
                break
        else:
            raise LPIPSWeightsError(f"{src_lin_pth}: no lin{k}.model.1.weight (keys: {sorted(lin_state)[:10]} ...)")
    model = LPIPS.from_state_dict(state, net, source=f"{src_trunk_pth} + {src_lin_pth}")
    return model.save(out)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m morpheus_core.metrics.lpips",
                                     description="Convert official LPIPS weights to lpips.safetensors.")
    parser.add_argument("--trunk", type=Path, required=True, help="torchvision alexnet-owt-7be5be79.pth or vgg16 .pth")
    parser.add_argument("--lin", type=Path, required=True, help="LPIPS v0.1 heads: weights/v0.1/alex.pth or vgg.pth")
    parser.add_argument("--out", type=Path, required=True, help=f"e.g. $MORPHEUS_MODELS/lpips/{LPIPS_FILE}")
    parser.add_argument("--net", choices=sorted(TRUNKS), default=None, help="trunk (default: from the keys)")
    args = parser.parse_args(argv)
    out = convert_lpips_checkpoint(args.trunk, args.lin, args.out, args.net)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
