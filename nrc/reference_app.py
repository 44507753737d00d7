"""The reference job: ``python -m nrc.reference_app`` (Hydra; ``conf/reference.yaml``), a converged ``pt``
reference rendered in parts that any Hydra launcher spreads over processes or cluster nodes, then merged
(:mod:`nrc.evaluation.reference_parts`).

    python -m nrc.reference_app scene=thick scene.integrator.spp=1024 reference.chunk_spp=64        # one process
    python -m nrc.reference_app -m scene=thick scene.integrator.spp=1024 reference.chunk_spp=64 \\
        reference.chunks=0:4,4:8,8:12,12:16 hydra/launcher=joblib                                  # four jobs

Each job renders its chunk range into ``<out>.parts/`` (resumable: run a killed job again); with
``reference.merge=auto`` a single run merges when every chunk is there, and a multirun merges once its jobs are
done (:class:`MergeAfterSweep`); ``reference.merge=only`` merges the parts found. Errors print one line naming
what is wrong (a missing chunk names the ranges to render again) and exit with status 2.

From Python, :func:`ensure_reference` is the same job in this process: the reference's path, rendered first when
missing (what the measurement scripts call).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from nrc.config import CONF_DIR, ConfigReader, absolute_paths, apply_threads
from nrc.errors import NRCError

log = logging.getLogger("nrc")


def settings(cfg: DictConfig) -> tuple[int, str, Path, str]:
    """``(chunk_spp, chunks, out, merge)`` of the ``reference`` block (unknown keys refused)."""
    return _settings(cfg)[:4]


def _settings(cfg: DictConfig) -> tuple[int, str, Path, str, float | None, bool]:
    """:func:`settings`, the ``rel_mse_floor`` target (``None``: render every chunk) and whether ``out`` was
    given."""
    from hydra.utils import to_absolute_path

    from nrc.evaluation.reference import default_reference_path

    r = ConfigReader(cfg.get("reference"), "reference")
    chunk_spp = r.get_int("chunk_spp", 64, lo=1)
    chunks = str(r.get_raw("chunks", "all"))
    out = r.get_optional_str("out")
    merge = r.get_choice("merge", ("auto", "only", "never"), "auto")
    floor = r.get_float("rel_mse_floor", None, lo=0.0, lo_open=True)
    r.finish()
    spp = int(cfg.scene.integrator.spp)
    path = Path(to_absolute_path(out)) if out else default_reference_path(cfg, spp)
    return chunk_spp, chunks, path, merge, floor, out is not None


def merge(cfg: DictConfig) -> Path:
    """Merge the parts of ``cfg``'s reference into its EXR; returns its path. With ``reference.rel_mse_floor`` the
    chunks there are merged once they reach it, into the EXR named by their spp (``reference.out`` if given)."""
    from nrc.evaluation.reference import default_reference_path, read_reference
    from nrc.evaluation.reference_parts import merge_parts, merge_to_floor

    chunk_spp, _, out, _, floor, named = _settings(cfg)
    if floor is None:
        merge_parts(cfg, out, chunk_spp, int(cfg.scene.integrator.spp))
    else:
        out = merge_to_floor(cfg, out, chunk_spp, int(cfg.scene.integrator.spp), floor,
                             lambda spp: out if named else default_reference_path(cfg, spp))
    ref = read_reference(out)
    print(f"wrote {out} ({ref.attrs['spp']} spp from {ref.attrs['parts']} part(s); rel_mse_floor: all "
          f"{ref.attrs['rel_mse_floor']:.3g}, medium {ref.attrs['rel_mse_floor_medium']:.3g})")
    return out


def job(cfg: DictConfig, multirun: bool) -> None:
    """Render this job's part (unless ``merge=only``), then merge when asked and every chunk is there."""
    from nrc.evaluation.reference import _chunk_count
    from nrc.evaluation.reference_parts import MissingChunks, parse_chunks, part_path, render_part

    absolute_paths(cfg)
    apply_threads(cfg.get("threads", "auto"))
    chunk_spp, chunks, out, when, floor, _ = _settings(cfg)
    spp = int(cfg.scene.integrator.spp)
    if when != "only":
        n_chunks = _chunk_count(chunk_spp, spp)
        span = parse_chunks(chunks, n_chunks)
        # a floor target stops one process early; a range among several jobs renders whole (the merge stops)
        part = render_part(cfg, out, chunk_spp, spp, span, floor_target=floor if len(span) == n_chunks else None)
        print(f"rendered chunks {part.first}:{part.first + part.done} into {part_path(out, span)}")
    if when == "only" or (when == "auto" and not multirun):
        try:
            merge(cfg)
        except MissingChunks as exc:
            if when == "only":
                raise
            print(f"not merged yet: {exc}")


def compose_reference(overrides: Sequence[str]) -> DictConfig:
    """The reference job's config (``conf/reference.yaml``) with ``overrides``, as ``python -m nrc.reference_app``
    sees it (outside a Hydra app)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="reference", overrides=list(overrides))


def ensure_reference(overrides: Sequence[str], spp: int, chunk_spp: int = 64, out: str | Path | None = None,
                     progress: bool = False) -> Path:
    """The path of the ``spp``-spp reference of the scene ``overrides`` (``out``, else the default path of
    :func:`nrc.evaluation.reference.default_reference_path`), rendered here first when it is missing: the job of
    ``python -m nrc.reference_app <overrides> scene.integrator.spp=<spp> reference.chunk_spp=<chunk_spp>`` in
    this process (resumable: its part stays beside the EXR until the merge)."""
    from nrc.evaluation.reference import _chunk_count
    from nrc.evaluation.reference_parts import render_part

    cfg = compose_reference([*overrides, f"scene.integrator.spp={int(spp)}",
                             f"reference.chunk_spp={min(int(chunk_spp), int(spp))}"])
    if out is not None:
        with open_dict(cfg):
            cfg.reference.out = str(out)
    absolute_paths(cfg)
    chunk, _, path, _, floor, _ = _settings(cfg)
    if path.is_file():
        return path
    n_chunks = _chunk_count(chunk, int(spp))
    render_part(cfg, path, chunk, int(spp), range(n_chunks), progress=progress, floor_target=floor)
    return merge(cfg)


@hydra.main(config_path=CONF_DIR, config_name="reference", version_base="1.3")
def _hydra_main(cfg: DictConfig) -> None:
    try:
        job(cfg, HydraConfig.get().mode == RunMode.MULTIRUN)
    except NRCError as exc:
        print(f"nrc.reference_app: error: {exc}", file=sys.stderr)
        sys.exit(2)


class MergeAfterSweep(Callback):
    """After a multirun of reference jobs (in the launching process, once every job has returned): merge their
    parts, with ``reference.merge=auto``. The config is the sweep's: its swept keys (the chunk ranges) are not
    needed to merge, and a sweep over anything else (two scenes) is not one reference: then nothing is merged."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        from nrc.app import sweep_jobs

        jobs = sweep_jobs(config)
        fixed = [[o for o in j if not o.startswith("reference.chunks=")] for j in jobs]
        if not jobs or any(f != fixed[0] for f in fixed):
            log.warning("the sweep varies more than reference.chunks: merge each reference with reference.merge=only")
            return
        cfg = OmegaConf.masked_copy(config, [k for k in config if k != "hydra"])  # a multirun's config: the
        absolute_paths(cfg)  # overrides that are not swept, applied (the chunk ranges are not needed to merge)
        try:
            if settings(cfg)[3] == "auto":
                merge(cfg)
        except NRCError as exc:
            print(f"nrc.reference_app: error: {exc}", file=sys.stderr)


def main() -> None:
    """Console-script entry point (``nrc-reference``)."""
    _hydra_main()


if __name__ == "__main__":
    main()
