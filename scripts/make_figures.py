"""Regenerate the README figures (docs/images/clouds.png, nrc_vs_pt.png/.json, sun.webp, figures.json).

Usage::

    python scripts/make_figures.py [--out docs/images] [--hero-spp 512] [--frames 30] [--anim-frames 36] ...

About 15 minutes on 2 cores with the defaults (the converged references are cached in data/references/ and
resume after an interruption). See nrc/evaluation/figures.py for what each figure shows.
"""



from nrc.evaluation.figures import main  # noqa: E402

if __name__ == "__main__":
    main()
