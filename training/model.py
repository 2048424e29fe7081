"""The bottom-centre detector of the paper: a MobileNet-v2 encoder, a feature-pyramid decoder up to the
output stride, and one two-convolution head per task.

Outputs at (H / stride, W / stride) for a (B, 1, H, W) grey input in [0, 1]:
    heat     (B, 1, h, w) sigmoid: bottom-centre heat map
    size     (B, 5, h, w) ReLU + SIZE_EPS: length, width, height (m); 2D box width, height
             (input pixels / shared.decode.BOX_SCALE_PX)
    heading  (B, 2, h, w) tanh: image-space vector from the footprint's rear towards its front
    axis     (B, 2, h, w) tanh, only with `axis_head`: the heading's axis as the doubled-angle vector
             (cos 2a, sin 2a) of the heading angle a: the same for a vehicle and its reverse
    vtype    (B, C, h, w) logits over VEHICLE_TYPES (the export wrapper applies softmax)
    offset   (B, 4, h, w) linear: (u - cell_u) / stride, (v - cell_v) / stride,
             (box_cx - u) / box_w, (box_cy - v) / box_h, with (u, v) the bottom centre in input pixels
    vote     (B, 2, h, w) linear, only with `vote_head`: (u - cell_u) / stride, (v - cell_v) / stride of the
             vehicle whose 2D box holds the cell, however far (training/targets.py, votes)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from training.sample import VEHICLE_TYPES

SIZE_EPS = 1e-3
STRIDES = (1, 2, 4)
ENCODER_STRIDE = 32
HEAT_PRIOR_BIAS = -4.0  # sigmoid(-4) ~ 0.018: heat starts near the background value
SIZE_INIT_BIAS = 1.0  # size starts near 1 (log ~ 0), away from the dead side of the ReLU
# MobileNet-v2 stages: expansion t, channels c, repeats n, first stride s (Sandler et al., Table 2)
MOBILENET_V2_STAGES = ((1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1), (6, 160, 3, 2),
                       (6, 320, 1, 1))
STEM_CHANNELS = 32


@dataclass(frozen=True)
class DetectorConfig:
    """Architecture and input normalisation; saved with every checkpoint and ONNX export.

    width_mult        MobileNet-v2 width multiplier
    decoder_channels  feature-pyramid channels
    head_channels     hidden channels of each head
    stride            output stride in input pixels (1, 2 or 4)
    input_mean/std    the network sees (x - input_mean) / input_std for x in [0, 1]
    num_types         vehicle classes
    input_long_side   images are shrunk so their longer side is at most this many pixels before the network
                      (never enlarged; then padded to a multiple of 32); training crops are taken at this scale
    axis_head         also predict the heading's axis (see the module docstring). Where the network cannot
                      yet tell a vehicle's front from its back, the squared error of the heading vector is
                      least for a zero vector, and the heading head learns nothing (measured: its loss stayed
                      at 0.8-1.0 of 2 over 5,000 steps, a yaw error of 60-90 degrees); the axis has no such
                      ambiguity. Decoding takes the direction from the axis and only its sign from the heading.
    vote_head         also predict, at every cell of a vehicle's 2D box, the way to its centre (trained by the
                      loss's vote term). With `detect.votes`, decoding moves a peak that lies far from the centre its
                      vote points at (a bus's near end) there, and reads the vehicle there (shared/decode.py).
    """

    width_mult: float = 0.5
    decoder_channels: int = 48
    head_channels: int = 24
    stride: int = 4
    input_mean: float = 0.5
    input_std: float = 0.25
    num_types: int = len(VEHICLE_TYPES)
    input_long_side: int = 640
    axis_head: bool = False
    vote_head: bool = False

    def __post_init__(self) -> None:
        if self.stride not in STRIDES:
            raise ValueError(f"stride must be one of {STRIDES}, got {self.stride}")
        if not self.width_mult > 0:
            raise ValueError(f"width_mult must be > 0, got {self.width_mult}")
        for name in ("decoder_channels", "head_channels", "num_types", "input_long_side"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.input_std > 0:
            raise ValueError(f"input_std must be > 0, got {self.input_std}")

    @property
    def heads(self) -> dict[str, int]:
        """Output channels per head."""
        heads = {"heat": 1, "size": 5, "heading": 2, "vtype": self.num_types, "offset": 4}
        return heads | ({"axis": 2} if self.axis_head else {}) | ({"vote": 2} if self.vote_head else {})


def _divisible(value: float, divisor: int = 8) -> int:
    """Round channels to a multiple of `divisor`, never more than 10 % below `value` (MobileNet's rule)."""
    rounded = max(divisor, int(value + divisor / 2) // divisor * divisor)
    return rounded + divisor if rounded < 0.9 * value else rounded


def _conv_bn_relu(cin: int, cout: int, kernel: int = 1, stride: int = 1, groups: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False),
                         nn.BatchNorm2d(cout), nn.ReLU6(inplace=True))


def _separable(cin: int, cout: int) -> nn.Sequential:
    """Depthwise 3x3 then pointwise 1x1, BN and ReLU."""
    return nn.Sequential(nn.Conv2d(cin, cin, 3, 1, 1, groups=cin, bias=False),
                         nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class InvertedResidual(nn.Module):
    """MobileNet-v2 block: 1x1 expansion, depthwise 3x3, linear 1x1 projection; residual when shapes allow."""

    def __init__(self, cin: int, cout: int, stride: int, expand: int) -> None:
        super().__init__()
        hidden = cin * expand
        layers: list[nn.Module] = [] if expand == 1 else [_conv_bn_relu(cin, hidden)]
        layers += [_conv_bn_relu(hidden, hidden, 3, stride, groups=hidden), nn.Conv2d(hidden, cout, 1, bias=False),
                   nn.BatchNorm2d(cout)]
        self.body = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x) if self.residual else self.body(x)


class MobileNetV2Encoder(nn.Module):
    """Grey-input MobileNet-v2 without its classifier; returns features at strides 2, 4, 8, 16 and 32."""

    def __init__(self, width_mult: float) -> None:
        super().__init__()
        cin = _divisible(STEM_CHANNELS * width_mult)
        self.stem = _conv_bn_relu(1, cin, 3, 2)
        stages, self.stage_strides, self.channels = [], [], {}
        stride = 2
        for t, c, n, s in MOBILENET_V2_STAGES:
            cout = _divisible(c * width_mult)
            blocks = []
            for i in range(n):
                blocks.append(InvertedResidual(cin, cout, s if i == 0 else 1, t))
                cin = cout
            stages.append(nn.Sequential(*blocks))
            stride *= s
            self.stage_strides.append(stride)
            self.channels[stride] = cout  # a later stage at the same stride replaces an earlier one
        self.stages = nn.ModuleList(stages)

    def forward(self, x: torch.Tensor) -> dict[int, torch.Tensor]:
        x = self.stem(x)
        feats = {}
        for stage, stride in zip(self.stages, self.stage_strides, strict=True):
            x = stage(x)
            feats[stride] = x
        return feats


class PyramidDecoder(nn.Module):
    """Top-down feature pyramid from stride 32 to `out_stride`: at each level a 1x1 lateral of the encoder
    feature (of the normalised image at stride 1) is added to the 2x upsampled coarser level, then smoothed
    by a depthwise-separable 3x3 convolution."""

    def __init__(self, channels: dict[int, int], out_stride: int, width: int) -> None:
        super().__init__()
        self.levels = [ENCODER_STRIDE]
        while self.levels[-1] > out_stride:
            self.levels.append(self.levels[-1] // 2)
        all_channels = {1: 1, **channels}
        self.lateral = nn.ModuleDict({str(s): nn.Sequential(nn.Conv2d(all_channels[s], width, 1, bias=False),
                                                            nn.BatchNorm2d(width)) for s in self.levels})
        self.smooth = nn.ModuleDict({str(s): _separable(width, width) for s in self.levels[1:]})

    def forward(self, image: torch.Tensor, feats: dict[int, torch.Tensor]) -> torch.Tensor:
        feats = {1: image, **feats}
        p = self.lateral[str(ENCODER_STRIDE)](feats[ENCODER_STRIDE])
        for s in self.levels[1:]:
            p = F.interpolate(p, scale_factor=2.0, mode="nearest") + self.lateral[str(s)](feats[s])
            p = self.smooth[str(s)](p)
        return p


class Head(nn.Module):
    """Two stacked convolutions: depthwise-separable 3x3 + BN + ReLU, then 1x1 to the outputs."""

    def __init__(self, cin: int, hidden: int, cout: int, bias: float = 0.0) -> None:
        super().__init__()
        self.hidden = _separable(cin, hidden)
        self.out = nn.Conv2d(hidden, cout, 1)
        nn.init.constant_(self.out.bias, bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.hidden(x))


class Detector(nn.Module):
    """forward((B, 1, H, W) float in [0, 1], H and W multiples of 32) -> dict of head outputs (see module doc)."""

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config or DetectorConfig()
        cfg = self.config
        self.encoder = MobileNetV2Encoder(cfg.width_mult)
        self.decoder = PyramidDecoder(self.encoder.channels, cfg.stride, cfg.decoder_channels)
        init_bias = {"heat": HEAT_PRIOR_BIAS, "size": SIZE_INIT_BIAS}
        self.heads = nn.ModuleDict({name: Head(cfg.decoder_channels, cfg.head_channels, c, init_bias.get(name, 0.0))
                                    for name, c in cfg.heads.items()})

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        h, w = x.shape[-2:]
        if not torch.jit.is_tracing() and (x.shape[1] != 1 or h % ENCODER_STRIDE or w % ENCODER_STRIDE):
            raise ValueError(f"input must be (B, 1, H, W), H and W multiples of {ENCODER_STRIDE}, got {tuple(x.shape)}")
        x = (x - self.config.input_mean) / self.config.input_std
        p = self.decoder(x, self.encoder(x))
        out = {name: head(p) for name, head in self.heads.items()}
        out["heat"] = torch.sigmoid(out["heat"])
        out["size"] = F.relu(out["size"]) + SIZE_EPS
        out["heading"] = torch.tanh(out["heading"])
        if "axis" in out:
            out["axis"] = torch.tanh(out["axis"])
        return out


class ExportWrapper(nn.Module):
    """The deployed graph: (B, 1, H, W) in [0, 1] -> (heat, size, heading, vtype_prob, offset[, axis][, vote]);
    `outputs` names them (the ONNX output names, and shared.decode.decode's arguments)."""

    OUTPUTS = ("heat", "size", "heading", "vtype_prob", "offset")

    def __init__(self, detector: Detector) -> None:
        super().__init__()
        self.detector = detector
        self.outputs = (self.OUTPUTS + (("axis",) if detector.config.axis_head else ())
                        + (("vote",) if detector.config.vote_head else ()))

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.detector(x)
        # softmax over channels spelled out: ONNX Runtime's Softmax on axis 1 transposes and costs ~1.5 ms at
        # 128 x 128 on one CPU thread, these element-wise ops ~0.2 ms
        logits = out["vtype"]
        e = torch.exp(logits - logits.amax(dim=1, keepdim=True))
        extra = tuple(out[name] for name in ("axis", "vote") if name in out)
        return (out["heat"], out["size"], out["heading"], e / e.sum(dim=1, keepdim=True), out["offset"], *extra)


def save_detector(model: Detector, path: str | Path, loss: dict | None = None) -> None:
    """Write the config and weights to one file, with the loss settings it was trained with (`loss`, the fields
    of training.loss.LossConfig) when given: fine-tuning takes them from there (`checkpoint_loss`)."""
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}  # loadable without a GPU
    with open(path, "wb") as f:  # Python's error names the path (torch's own writer does not)
        torch.save({"config": asdict(model.config), "state_dict": state, **({"loss": loss} if loss else {})}, f)


def checkpoint_loss(path: str | Path) -> dict | None:
    """The loss settings recorded in a file written by save_detector, None for a file without them (older
    checkpoints: the paper's loss and betas unless the run said otherwise)."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises unpickling and zip errors of its own kinds
        raise ValueError(f"{path}: not a roadside detector checkpoint ({type(exc).__name__})") from None
    loss = ckpt.get("loss") if isinstance(ckpt, dict) else None
    return dict(loss) if isinstance(loss, dict) else None


def load_detector(path: str | Path) -> Detector:
    """Read a file written by save_detector; the model is returned in eval mode."""
    if not Path(path).is_file():
        raise ValueError(f"model file not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
        model = Detector(DetectorConfig(**ckpt["config"]))
        model.load_state_dict(ckpt["state_dict"])
    except Exception as exc:  # torch raises unpickling, zip, key and shape errors of its own kinds
        raise ValueError(f"{path}: not a roadside detector checkpoint ({type(exc).__name__}: "
                         f"{str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ''})") from None
    return model.eval()


def count_macs(model: nn.Module, h: int, w: int) -> int:
    """Multiply-accumulates of all Conv2d and Linear layers for one (1, 1, h, w) input."""
    total = 0

    def conv_hook(m: nn.Conv2d, _inp: tuple, out: torch.Tensor) -> None:
        nonlocal total
        total += out.numel() * (m.in_channels // m.groups) * m.kernel_size[0] * m.kernel_size[1]

    def linear_hook(m: nn.Linear, _inp: tuple, out: torch.Tensor) -> None:
        nonlocal total
        total += out.numel() * m.in_features

    handles = []
    for m in model.modules():
        if isinstance(m, nn.Conv2d):
            handles.append(m.register_forward_hook(conv_hook))
        elif isinstance(m, nn.Linear):
            handles.append(m.register_forward_hook(linear_hook))
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            model(torch.zeros(1, 1, h, w))
    finally:
        for handle in handles:
            handle.remove()
        model.train(was_training)
    return total
