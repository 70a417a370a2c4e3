"""The compiled part of ar_anchor: one C extension (the pose polish, ar_anchor/track/_lm.c). Everything else
is declared in pyproject.toml. ``optional``: a machine that cannot compile it still installs ar_anchor,
which then runs the same computation in numpy (ar_anchor/track/kernels.py)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("ar_anchor.track._lm", ["ar_anchor/track/_lm.c"], extra_compile_args=["-O2"], optional=True)
    ]
)
