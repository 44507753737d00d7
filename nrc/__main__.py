"""``python -m nrc``: the Hydra application (see :mod:`nrc.app`)."""

from nrc.app import main

main()
