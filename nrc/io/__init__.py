"""Image input/output: linear EXR files and tone-mapped PNG previews."""

from nrc.io.exr import read_exr, write_exr
from nrc.io.png import tonemap, write_png

__all__ = ["read_exr", "write_exr", "tonemap", "write_png"]
