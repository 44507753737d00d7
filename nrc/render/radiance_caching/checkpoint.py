"""The NRC checkpoint file: what it holds, how it is written and read, and when a resume is refused.

File layout: the 8-byte magic ``NRCCKPT\\n``, the 32-byte SHA-256 of the rest, then the zlib-compressed
(level 1) payload, a ``torch.save`` of tensors and plain data only (dicts, lists, str, int, float, bool,
None), so it loads with ``torch.load(weights_only=True)``: no pickled code runs. Nearly all of a checkpoint
is the cache's hash tables, four times over (the raw weights, their EMA and Adam's two moments, all needed
for an exact resume); compression halves a young cache's file (zeros in the moments of untouched entries:
52.9 -> 28.5 MB with 2^19-row tables, +0.8 s per write; `log2_hashmap_size: auto` makes them smaller). Writes go to ``<name>.tmp`` and are renamed over
the file (atomic on POSIX), so an interrupted write leaves the previous checkpoint intact.

Payload keys: ``version`` (:data:`VERSION`), ``frame`` (frames done), ``cache`` (raw weights, EMA, Adam
moments, step counters), ``ring`` (training records), ``accum`` and ``n_accum`` (the accumulated image),
``history`` (per-frame statistics) and ``config`` (the run's resolved config as YAML).

A resume compares the stored config with the current one and refuses any difference except in the keys of
:data:`MAY_CHANGE` (how many frames, logging, checkpoint cadence, the reference, the preview, the device).
Every problem is one :class:`~nrc.errors.NRCError` naming the file and what is wrong.
"""

from __future__ import annotations

import hashlib
import io
import json
import zlib
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from nrc.errors import ConfigError
from nrc.io.atomic import write_atomically

MAGIC = b"NRCCKPT\n"
VERSION = 2
KEYS = ("version", "frame", "cache", "ring", "accum", "n_accum", "history", "config")
MAY_CHANGE = ("frames", "renderer.resume", "renderer.checkpoint_every", "renderer.log", "renderer.reference",
              "renderer.backend", "tonemap", "exposure", "denoise", "device")
COMPARED = ("scene", "renderer", "transmittance", "cache", "encoding", "extra_inputs", "batch_filter", "frames",
            "device", "tonemap", "exposure")


class CheckpointError(ConfigError):
    """A checkpoint that cannot be used (the message names the file)."""


def plain(data: Any) -> Any:
    """``data`` as JSON-like plain Python (numpy scalars to int/float), loadable with ``weights_only``."""
    return json.loads(json.dumps(data, default=lambda v: v.item() if hasattr(v, "item") else str(v)))


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> int:
    """Write ``state`` (the payload keys but ``version``) atomically; returns the file size in bytes."""
    path = Path(path)
    buf = io.BytesIO()
    torch.save({"version": VERSION, **state}, buf)
    payload = zlib.compress(buf.getvalue(), 1)
    write_atomically(path, lambda f: f.write(MAGIC + hashlib.sha256(payload).digest() + payload), fsync=True)
    return len(MAGIC) + 32 + len(payload)


def load_checkpoint(path: str | Path, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Read and verify a checkpoint (magic, checksum, format version, keys)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"renderer.resume: no such checkpoint {path}")
    data = path.read_bytes()
    if len(data) < len(MAGIC) + 32 or data[:len(MAGIC)] != MAGIC:
        raise CheckpointError(f"renderer.resume: {path} is not an nrc checkpoint (no NRCCKPT header: another "
                              "file, or written by nrc before checkpoint format 2)")
    digest, payload = data[len(MAGIC):len(MAGIC) + 32], data[len(MAGIC) + 32:]
    if hashlib.sha256(payload).digest() != digest:
        raise CheckpointError(f"renderer.resume: {path} is corrupted (checksum mismatch: truncated or altered "
                              f"after it was written, {len(data)} bytes)")
    try:
        state = torch.load(io.BytesIO(zlib.decompress(payload)), map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is one message
        raise CheckpointError(f"renderer.resume: {path} cannot be read ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else 'no detail'})") from None
    if not isinstance(state, dict) or state.get("version") != VERSION:
        found = state.get("version") if isinstance(state, dict) else type(state).__name__
        raise CheckpointError(f"renderer.resume: {path} has checkpoint format version {found}, this nrc reads "
                              f"version {VERSION}")
    missing = [k for k in KEYS if k not in state]
    if missing:
        raise CheckpointError(f"renderer.resume: {path} lacks {', '.join(missing)}")
    return state


def _flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out if node else {prefix[:-1]: {}}
    return {prefix[:-1]: node}


def config_differences(stored_yaml: str, current: Any) -> list[str]:
    """Dotted keys whose values differ between the stored config and ``current`` (outside :data:`MAY_CHANGE`)."""
    stored = OmegaConf.to_container(OmegaConf.create(stored_yaml or "{}"), resolve=True)
    now = OmegaConf.to_container(current, resolve=True) if OmegaConf.is_config(current) else dict(current)
    a = _flatten({k: stored.get(k) for k in COMPARED if k in stored or k in now})
    b = _flatten({k: now.get(k) for k in COMPARED if k in stored or k in now})
    diff = [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    return [k for k in diff if not any(k == m or k.startswith(m + ".") for m in MAY_CHANGE)]


def check_config(path: str | Path, stored_yaml: str, current: Any) -> None:
    """Refuse to resume a checkpoint of another configuration, naming the differing keys."""
    diff = config_differences(stored_yaml, current)
    if diff:
        shown = ", ".join(diff[:6]) + (f" and {len(diff) - 6} more" if len(diff) > 6 else "")
        raise ConfigError(f"renderer.resume: {path} was written with another configuration ({shown} differ); "
                          f"only {', '.join(MAY_CHANGE[:1] + MAY_CHANGE[2:])} may change on resume")
