"""Neural radiance cache (Müller et al. 2021) for participating media: encodings, MLP, training.

Public API: :func:`build_radiance_cache` and :class:`RadianceCache`; the pieces (encodings, loss,
EMA, input builder) are importable from their modules.
"""

from nrc.cache.radiance_cache import RadianceCache, build_radiance_cache

__all__ = ["RadianceCache", "build_radiance_cache"]
