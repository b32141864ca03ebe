"""monose3: markerless camera-to-robot pose estimation with MonoSE(3)-Diffusion."""

from monose3.errors import Monose3Error

__version__ = "0.1.0"
__all__ = ["Monose3Error", "__version__"]
