"""photonpano-phasecorr: an example third-party photonpano locator (phase correlation)."""

__version__ = "0.1.0"
