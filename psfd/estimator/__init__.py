"""Pure numerics of PSF estimation: arrays in, arrays out.

Nothing here imports the drivers, the daemon or the catalogue.
"""
