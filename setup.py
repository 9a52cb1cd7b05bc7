"""Builds flight_sw's compiled kernels (SGM: flight_sw/_sgmc.c; P(safe) trees: flight_sw/_treesc.c);
everything else is in pyproject.toml.

The kernels are optional at run time: flight_sw.sgm and flight_sw.psafe fall back to their numpy
references if an extension is missing (docs/benchmarks/pipeline.md measures both).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("flight_sw._sgmc", ["flight_sw/_sgmc.c"], extra_compile_args=["-O3", "-std=c99"], optional=True),
        Extension("flight_sw._treesc", ["flight_sw/_treesc.c"], extra_compile_args=["-O3", "-std=c99"], optional=True),
    ]
)
