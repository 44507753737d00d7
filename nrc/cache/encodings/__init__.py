"""Input encodings of the radiance cache (tiny-cuda-nn conventions); build them with :mod:`.factory`."""
