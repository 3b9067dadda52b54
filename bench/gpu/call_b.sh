#!/bin/bash
# On the same GPU machine after call_a.sh, carrying .dev/b: pycolmap + dask, the CUDA tests, then the production and default presets on /opt/gp's capture.
S=/opt/devsite; t0=$(date +%s)
test -d $S/open3d -a -d /opt/gp/work/capture || { echo "call A's install or capture is gone (a fresh machine)"; exit 21; }
tar -xJf .dev/b/pyc.tar.xz -C $S || exit 22
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target $S .dev/b/whl/*.whl || exit 23
export PYTHONPATH=$S:$PWD PYTHONUNBUFFERED=1
mkdir -p ../shared/data/hdri && cp .dev/b/hdri/*.hdr ../shared/data/hdri/
python3 -c "import pycolmap, dask, distributed, xatlas; print('pycolmap', pycolmap.__version__, 'dask', dask.__version__)" || exit 24
echo "install $(( $(date +%s) - t0 )) s"
timeout 100 python3 -m pytest -q -p no:cacheprovider tests/unit/numerics/test_cuda_paths.py tests/unit/baselines/test_baselines_cuda.py 2>&1 | tail -15 | tee $OUT/cuda_tests.txt
nvidia-smi --query-gpu=memory.used --format=csv
timeout 430 python3 bench/bench_gpu_production.py --out /opt/gp --work /opt/gp/work --capture /opt/gp/work/capture --presets production,default --budget-s $(( 540 - ($(date +%s) - t0) ))
cp /opt/gp/bench_gpu_production.{json,md} /opt/gp/*.log $OUT/ 2>/dev/null; ls $OUT
echo "call B total $(( $(date +%s) - t0 )) s"
