"""nrc: neural radiance caching for heterogeneous participating media, in pure PyTorch."""

__version__ = "0.1.0"
