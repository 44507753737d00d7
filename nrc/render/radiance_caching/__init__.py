"""``renderer=nrc``: neural radiance caching, frame after frame (``docs/nrc.md``).

* :mod:`~nrc.render.radiance_caching.renderer` -- the frame loop (trace, infer, train), checkpoints and resume;
* :mod:`~nrc.render.radiance_caching.paths` -- the frame's render and training paths on the shared transport core;
* :mod:`~nrc.render.radiance_caching.settings` -- the validated ``renderer`` block;
* :mod:`~nrc.render.radiance_caching.termination` -- when a render path hands over to the cache;
* :mod:`~nrc.render.radiance_caching.debias` -- the cache as a control variate (unbiased frames, ``renderer.debias``);
* :mod:`~nrc.render.radiance_caching.training_set`, :mod:`~nrc.render.radiance_caching.ring_buffer` -- training records and targets;
* :mod:`~nrc.render.radiance_caching.inference_filter`, :mod:`~nrc.render.radiance_caching.batch_filter` -- which queries and training
  batches are evaluated;
* :mod:`~nrc.render.radiance_caching.frame_log` -- TensorBoard logs.
"""

from nrc.render.radiance_caching.renderer import NRCRenderer

__all__ = ["NRCRenderer"]
