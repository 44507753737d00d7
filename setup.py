"""Packaging hook (metadata lives in pyproject.toml): the wheel carries the Hydra configs of ``conf/`` as
``nrc/conf/``, so an installed nrc runs ``python -m nrc`` from any directory."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildPyWithConf(build_py):
    def run(self) -> None:
        super().run()
        shutil.copytree(Path(__file__).parent / "conf", Path(self.build_lib) / "nrc" / "conf", dirs_exist_ok=True)


setup(cmdclass={"build_py": BuildPyWithConf})
