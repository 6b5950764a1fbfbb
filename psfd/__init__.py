"""psfd: unattended sub-pixel camera PSF measurement."""

__version__ = "0.1.0"
