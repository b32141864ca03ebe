"""The denoiser designs, one class each (``NetworkConfig.design``; docs/DESIGNS.md)."""

from __future__ import annotations

from monose3.method.config import DESIGNS, NetworkConfig
from monose3.method.denoiser import Denoiser
from monose3.method.designs.concat import Concat, ConcatGrid
from monose3.method.designs.cost_volume import CostVolume, FlowSolve
from monose3.method.designs.evidence import EvidenceNet, EvidenceSolve

DESIGN_CLASSES: dict[str, type[Denoiser]] = {
    "concat": Concat,
    "concat-grid": ConcatGrid,
    "cost-volume": CostVolume,
    "flow-solve": FlowSolve,
    "evidence": EvidenceNet,
    "evidence-solve": EvidenceSolve,
}
FIELD_DESIGNS = tuple(name for name, cls in DESIGN_CLASSES.items() if cls.predicts_field)


def design_inputs(config: NetworkConfig) -> str:
    """What the design ``config.design`` compares: "pixels" or "parser" (:attr:`Denoiser.inputs`)."""
    if config.design not in DESIGN_CLASSES:
        raise ValueError(f"unknown denoiser design {config.design!r}; choose one of {DESIGNS}")
    return DESIGN_CLASSES[config.design].inputs


def build_denoiser(config: NetworkConfig, pretrained: bool = True) -> Denoiser:
    """The denoiser ``config.design`` names (one of :data:`~monose3.method.config.DESIGNS`);
    ``pretrained``: a pretrained trunk starts from its ImageNet weights (off to load a checkpoint)."""
    if config.design not in DESIGN_CLASSES:
        raise ValueError(f"unknown denoiser design {config.design!r}; choose one of {DESIGNS}")
    return DESIGN_CLASSES[config.design](config, pretrained=pretrained)
