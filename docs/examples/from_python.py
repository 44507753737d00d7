"""nrc from Python, notebook style: render, change one value, render again, plot; then watch the cache learn.

Run it as a script (``python docs/examples/from_python.py [out_dir]``, default ``outputs/from_python``) or paste
its cells into a notebook. It writes ``albedo.png`` (two path traces side by side) and ``learning.png`` (NRC's
training loss and its image mean, frame by frame) into ``out_dir``. ``SIZE`` keeps it under a minute on 2 cores.
"""

# %% set-up
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import nrc  # noqa: E402

out_dir = Path(sys.argv[1] if len(sys.argv) > 1 else "outputs/from_python")
out_dir.mkdir(parents=True, exist_ok=True)
SIZE = {"scene.camera.width": 48, "scene.camera.height": 27, "scene.volume.procedural.resolution": 24,
        "denoise": "none"}


def show(image: np.ndarray) -> np.ndarray:
    """Linear RGB to a display image (exposure from the 99th percentile, gamma 2.2)."""
    return np.clip(image / max(np.percentile(image, 99), 1e-6), 0, 1) ** (1 / 2.2)


# %% render, change one value, render again
base = nrc.run({**SIZE, "scene.integrator.spp": 4})
darker = nrc.run({**SIZE, "scene.integrator.spp": 4, "scene.volume.albedo": 0.8})
print(f"path tracer: {base.metrics['time_render_s']:.1f} s, mean {base.image.mean():.4f} -> albedo 0.8: "
      f"{darker.image.mean():.4f} (backend {base.metrics['backend']}, {base.metrics['threads']} threads)")
fig, axes = plt.subplots(1, 2, figsize=(8, 2.6))
for ax, r, title in zip(axes, (base, darker), ("albedo 1.0 (default)", "albedo 0.8")):
    ax.imshow(show(r.image))
    ax.set_title(title)
    ax.axis("off")
fig.savefig(out_dir / "albedo.png", dpi=100, bbox_inches="tight")

# %% NRC frame by frame: the cache learning (stop early whenever you like)
losses, means = [], []
for frame in nrc.frames({**SIZE, "frames": 8, "renderer.log.tensorboard": False}):
    losses.append(frame.stats["loss"])
    means.append(float(frame.image.mean()))
print(f"NRC: {len(losses)} frames, loss {losses[0]:.3g} -> {losses[-1]:.3g}")
fig, (a, b) = plt.subplots(1, 2, figsize=(8, 2.6))
a.semilogy(losses)
a.set_xlabel("frame")
a.set_ylabel("training loss")
b.plot(means, label="NRC frame")
b.axhline(base.image.mean(), color="k", lw=0.8, label="path tracer, 4 spp")
b.set_xlabel("frame")
b.set_ylabel("image mean")
b.legend()
fig.savefig(out_dir / "learning.png", dpi=100, bbox_inches="tight")
print(f"wrote {out_dir / 'albedo.png'} and {out_dir / 'learning.png'}")
