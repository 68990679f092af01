#!/usr/bin/env bash
# One command for the batch bench on a machine with a GPU (jaxbvh.batch, bench/bench_batch.py).
#
#   bench/gpu.sh                 # 1,000 meshes of 200-5,000 triangles, build + pipeline, tinybvh beside
#   MESHES=200 bench/gpu.sh      # fewer meshes
#
# Needs jax with CUDA (pip install -U "jax[cuda12]") in the active Python, and ../shared beside
# the repository (the meshes, the tinybvh header). Writes bench/results/batch_gpu.{json,md,png}.
# The batch axis is split over every visible GPU (jax.devices()); pick them with CUDA_VISIBLE_DEVICES.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY=${PY:-python}
"$PY" -c 'import jax, sys; d = jax.devices(); print("devices:", d); sys.exit(0 if d[0].platform == "gpu" else "no GPU visible to jax (install jax[cuda12])")'
# the GPU holds the whole batch: let XLA take memory as it needs it rather than 75% up front
export XLA_PYTHON_CLIENT_PREALLOCATE=${XLA_PYTHON_CLIENT_PREALLOCATE:-false}
PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} "$PY" bench/bench_batch.py --meshes "${MESHES:-1000}" \
  --memory-mb "${MEMORY_MB:-16384}" --sizes 1 16 128 "${MESHES:-1000}" --tag gpu "$@"
