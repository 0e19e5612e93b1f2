"""The cGAN normal-map refiner of Choi et al. 2021: networks, losses, data."""

from pathlib import Path

SHIPPED_WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "refiner.pt"
"""The generator shipped in the package (``make ship`` replaces it in place)."""
