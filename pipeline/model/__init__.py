"""The cGAN normal-map refiner of Choi et al. 2021: networks, losses, data."""
