"""The one transport core of ``renderer=pt`` and ``renderer=nrc``: a wavefront of per-slot paths.

* :mod:`~nrc.render.wavefront.state` -- the named per-slot state and its packed layout;
* :mod:`~nrc.render.wavefront.step` -- the transport step (tracking step, vertex), the same code eager or compiled;
* :mod:`~nrc.render.wavefront.machine` -- compiled or eager execution, one compile per process and structure;
* :mod:`~nrc.render.wavefront.graphs` -- the step's calls through CUDA graphs of padded slot buckets
  (``renderer.cuda_graphs``);
* :mod:`~nrc.render.wavefront.driver` -- refill, harvest, compaction, the vertex pass and the shadow queue;
* :mod:`~nrc.render.wavefront.setup` (:func:`build_core`) -- majorants, the step, its scene inputs and the backend choice.
"""

from nrc.render.wavefront.setup import BACKENDS, Core, build_core, camera_paths, camera_rays, wavefront_majorants

__all__ = ["BACKENDS", "Core", "build_core", "camera_paths", "camera_rays", "wavefront_majorants"]
