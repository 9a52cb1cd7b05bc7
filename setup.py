"""Builds flight_sw's compiled SGM kernel (flight_sw/_sgmc.c); everything else is in pyproject.toml.

The kernel is optional at run time: flight_sw.sgm falls back to its numpy reference if the
extension is missing (docs/benchmarks/pipeline.md measures both).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("flight_sw._sgmc", ["flight_sw/_sgmc.c"], extra_compile_args=["-O3", "-std=c99"], optional=True)
    ]
)
