#!/bin/bash
# On the GPU machine, carrying .dev/a (bench/gpu/make_bundle.sh): open3d + the simulator's packages, the GPU field-step bench, the capture simulated into /opt/gp.
S=/opt/devsite; mkdir -p $S /opt/gp
t0=$(date +%s)
tar -xJf .dev/a/o3d.tar.xz -C $S || exit 11
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target $S .dev/a/whl/*.whl || exit 12
export PYTHONPATH=$S:$PWD PYTHONUNBUFFERED=1
mkdir -p ../shared/data/meshes && cp -r .dev/a/meshes/* ../shared/data/meshes/ || echo "WARN: ../shared not writable"
echo "install $(( $(date +%s) - t0 )) s"; pwd; nproc; free -g | head -2
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
python3 -c "import open3d, torch, OpenEXR, rawpy, colour, trimesh, numpy; print('open3d', open3d.__version__, 'torch', torch.__version__, torch.cuda.is_available(), 'numpy', numpy.__version__)" || exit 13
timeout 90 python3 bench/bench_gpu.py --out $OUT/gpu
timeout 240 python3 bench/bench_gpu_production.py --out /opt/gp --work /opt/gp/work --probe-width 256 --widths 768,1024,1280,1536,2048 --simulate-budget-s 150 --simulate-only
cp /opt/gp/bench_gpu_production.json $OUT/ 2>/dev/null
du -sh /opt/gp/work/capture; echo "call A total $(( $(date +%s) - t0 )) s"
