"""Configuration dataclasses and their named presets.

``paper`` follows the paper (ResNet34, 640x480 input, 320x240 render). ``cpu`` is the same
code path sized to learn something useful in about an hour on a 2-core machine. Both use the
paper's ``concat`` denoiser; ``NetworkConfig.design`` selects the others (DESIGNS).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from typing import Any

from monose3.errors import Monose3Error


@dataclass(frozen=True)
class DiffusionConfig:
    """The forward process (Sec. III-B) and its schedule (Sec. IV-A)."""

    num_steps: int = 100  # T, linear schedule
    beta_start: float = 1e-4
    beta_end: float = 0.02
    c_z: float = 1.5  # depth normalisation, metres (Eq. 4)
    # gamma: our reading of the paper's undefined gamma = 3. The translation part of the
    # normalised pose is multiplied by gamma before diffusion (and divided after), so its
    # noise is 1/gamma of the rotation part's: rotations spread over SO(3) while positions
    # stay in the view frustum. gamma = 1 is the plain Eq. 5. See benchmarks/visdiff.py.
    gamma: float = 3.0
    noise: str = "visdiff"  # "visdiff" (Eq. 4-7) or "fixper" (RoboPose's fixed perturbation)
    fixper_rot_std_deg: float = 60.0
    fixper_trans_std: float = 0.1


# The denoiser architectures (method.denoiser): "concat" is the paper's; see docs/DESIGNS.md.
# The study's other candidates (siamese, siamese-corr, siamese-pose, siamese-grid; the abs6d
# rotation output) lost and were removed after round 4; DESIGNS.md names the commit that has them.
DESIGNS = (
    "concat",
    "concat-grid",
    "cost-volume",
    "flow-solve",
    "evidence",
    "evidence-solve",
)  # classes: monose3.method.designs
FIELD_STRIDES = (4, 8)
# The denoiser's trunks: ResNets from scratch, or EfficientNet-Lite0 with its ImageNet weights
# (monose3.networks.backbone), which only the designs that compare through cost volumes take.
BACKBONES = ("resnet18", "resnet34", "efficientnet-lite0")
PRETRAINED_TRUNK_DESIGNS = ("cost-volume", "flow-solve")
# The crop leaves the robot a margin of (1 - 1 / 1.4) / 2 = 14 % of its size on each side
# (RoboPose's 1.4); moved by more, the crop cuts the robot off.
MAX_CROP_JITTER = 0.14
# How the network's rotation outputs are read: "6d" is the paper's offset of the 6D rotation.
ROTATION_OUTPUTS = ("6d", "so3")


@dataclass(frozen=True)
class NetworkConfig:
    backbone: str = "resnet34"
    render_size: tuple[int, int] = (320, 240)  # (w, h) of the render and of the crop
    input_size: tuple[int, int] = (640, 480)  # (w, h) every input image is brought to
    time_embedding_dim: int = 4  # C_emb
    # "concat": the paper's ResNet over concat(render, crop, C_emb) (Sec. III-C). The others
    # (see DESIGNS, docs/DESIGNS.md) compare render and crop features through cost volumes.
    design: str = "concat"
    # "6d": the rotation outputs are an offset from the identity's 6D vector (the paper's
    # 6D rotation, Gram-Schmidt). "so3": a rotation vector (radians) mapped to the same 6D
    # layout inside the network, so no output direction leaves dR unchanged (denoiser.so3_raw).
    rotation_output: str = "6d"
    # flow-solve: the stride (crop pixels per cell) of its displacement field, 8 or 4 (FIELD_STRIDES).
    field_stride: int = 8


@dataclass(frozen=True)
class TrainConfig:
    batch_size: int = 16
    lr: float = 3e-4
    warmup_steps: int = 500
    max_steps: int = 300_000
    grad_clip: float = 10.0
    # Weight of Eq. 10's rotation part in the training loss (1: the paper's sum). At the identity
    # update its gradient on the network's outputs is about 6x smaller than xy's and z's.
    rot_weight: float = 1.0
    # A curriculum over t (None: the paper's t ~ U{1..T} from the start): draw t <= t_max, and
    # raise that cap linearly to T over t_curriculum_steps (0: keep it). Rotation differences
    # are visible at small t; at t > 50 they are ~70 deg and swamp the learnable gradients
    # (docs/DESIGNS.md).
    t_max: int | None = None
    t_curriculum_steps: int = 0
    # Weight of the cost-volume design's auxiliary loss (method.loss.flow_targets; not in the
    # paper): where each part of the robot moves between render and crop, per cell.
    flow_weight: float = 0.0
    # Crop jitter (not in the paper): each training crop moves by up to this fraction of its
    # size, uniformly in x and y, with the render (same crop intrinsics). Centred on H_t, the
    # robot's offset in the crop *is* v_xy, so a network can read xy off the crop alone and
    # never compare; moved at random, the offset says nothing without the render. 0: RoboPose's rule.
    crop_jitter: float = 0.0
    checkpoint_every: int = 500
    log_every: int = 20
    num_workers: int = 4
    seed: int = 0


@dataclass(frozen=True)
class InferenceConfig:
    ddim_steps: int = 5  # K reverse-diffusion steps (Alg. 2)
    direct_steps: int = 5  # M direct-regression refinements
    eta: float = 1.0
    tracking_t: int = 10  # small t for 1-step tracking
    prior_t: int = 30  # where the reverse process starts when refining a user's approximate pose


@dataclass(frozen=True)
class Config:
    preset: str = "paper"
    robot: str = "panda"
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    inference: InferenceConfig = field(default_factory=InferenceConfig)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> Config:
        return _from_dict(Config, data)


def _from_dict(cls: type, data: dict[str, Any]) -> Any:
    kwargs = {}
    for f in fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        default = f.default_factory() if callable(f.default_factory) else f.default
        if is_dataclass(default):
            value = _from_dict(type(default), value)
        elif isinstance(default, tuple):
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


PRESETS: dict[str, Config] = {
    "paper": Config(),
    "cpu": Config(
        preset="cpu",
        network=NetworkConfig(backbone="resnet18", render_size=(128, 96), input_size=(320, 240)),
        train=TrainConfig(batch_size=16, warmup_steps=200, checkpoint_every=200, num_workers=1),
    ),
    # The evidence denoiser (method.designs.evidence): the parser's mask and keypoints against the
    # silhouette and keypoints at H_t, at 64x48, trained on a cache of the parser's outputs.
    "evidence": Config(
        preset="evidence",
        network=NetworkConfig(backbone="resnet18", render_size=(64, 48), input_size=(320, 240), design="evidence"),
        train=TrainConfig(batch_size=64, lr=1e-3, warmup_steps=200, checkpoint_every=500, num_workers=0),
    ),
}


# ``monose3 train``'s default preset: sized for the CPU machine most users start on. ``Config()``
# itself is the paper's configuration (the ``paper`` preset).
TRAIN_PRESET = "cpu"


def get_preset(name: str, **overrides: Any) -> Config:
    """A preset by name; ``overrides`` replace top-level fields (e.g. ``robot='kuka'``)."""
    if name not in PRESETS:
        raise Monose3Error(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return replace(PRESETS[name], **overrides)


def with_section(config: Config, section: str, **values: Any) -> Config:
    """Copy of ``config`` with fields of one section (``diffusion``, ``train``, ...) replaced."""
    return replace(config, **{section: replace(getattr(config, section), **values)})
