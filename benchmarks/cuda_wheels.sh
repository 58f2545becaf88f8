#!/usr/bin/env bash
# The wheels a CUDA machine without network lacks for the suite and benchmarks/gpu.py (its image has
# torch, numpy, scipy, matplotlib, pytest, pytest-xdist and the like; not these), for CPython 3.12 on
# x86-64 Linux, downloaded here into DIR (about 41 MB), for benchmarks/cuda_check.sh's WHEELS=DIR.
#
#   bash benchmarks/cuda_wheels.sh DIR
#
# largesteps (a benchmark peer) has no wheel: its tests skip there.
set -euo pipefail
dir=${1:?usage: bash benchmarks/cuda_wheels.sh DIR}
mkdir -p "$dir"
# typer 0.29 needs pydantic, which the image lacks (2026-11-27: the CLI's tests failed there without it).
packages=(trimesh libigl cholespy OpenEXR embreex pycpd pdoc "typer>=0.28"
          pydantic pydantic-core annotated-types typing-inspection typing-extensions
          dask distributed partd locket tblib zict tornado)
platforms=()
for platform in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
                manylinux1_x86_64; do
    platforms+=(--platform "$platform")
done
for package in "${packages[@]}"; do
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        "${platforms[@]}" -d "$dir" "$package"
done
ls "$dir"
