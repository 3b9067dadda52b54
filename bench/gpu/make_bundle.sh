#!/bin/bash
# Build the offline bundles that bench/bench_gpu_production.py needs on a GPU machine that has Python 3.12, torch,
# numpy, scipy, pandas, pyarrow, scikit-image, matplotlib and pytest but none of the project's other packages and
# no network (the workplace's H200 machines), each under 64 MiB so that it travels in one call:
#   .dev/a: open3d (the CPU build without its GUI resources and TF/torch ops, xz: 38 MB), colour-science, rawpy,
#           OpenEXR, trimesh, numexpr, the MakeHuman mesh and skins                       (simulation)
#   .dev/b: pycolmap (xz: 21 MB), dask, distributed and their missing dependencies, xatlas, the HDR maps (the runs)
# Usage (repository root, with ../shared beside it): bash bench/gpu/make_bundle.sh; then on the GPU machine
# `bash bench/gpu/call_a.sh` carrying .dev/a and, while it is still up, `bash bench/gpu/call_b.sh` carrying .dev/b.
set -euo pipefail
PY=${PY:-.venv/bin/python}
ROOT=$(pwd); W=$(mktemp -d)
EXCLUDE=$(git rev-parse --git-path info/exclude); mkdir -p "$(dirname "$EXCLUDE")"
grep -qx '/.dev/' "$EXCLUDE" 2>/dev/null || echo '/.dev/' >> "$EXCLUDE"
pins() { grep -iE "^($1)==" requirements.lock | tr '\n' ' '; }
fetch() { "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux_2_5_x86_64 \
  --platform manylinux1_x86_64 -d "$1" "${@:2}"; }
rm -rf .dev/a .dev/b; mkdir -p .dev/a/whl .dev/a/meshes .dev/b/whl .dev/b/hdri
fetch "$W" "open3d-cpu==$(grep -i '^open3d==' requirements.lock | cut -d= -f3)" "pycolmap==$(grep -i '^pycolmap==' requirements.lock | cut -d= -f3)"
fetch .dev/a/whl $(pins 'colour-science|OpenEXR|numexpr') rawpy trimesh
fetch .dev/b/whl $(pins 'dask|distributed|partd|locket|tblib|tornado|zict') xatlas
(cd "$W" && mkdir o3d pyc && unzip -q open3d_cpu-*.whl -d o3d && unzip -q pycolmap-*.whl -d pyc)
rm -rf "$W"/o3d/open3d/{resources,open3d_tf_ops.so,open3d_torch_ops.so,examples,labextension,nbextension,agent_skills}
# plotly (the notebook visualiser) is not on those machines: its import becomes optional.
"$PY" - "$W/o3d/open3d/visualization/__init__.py" <<'PYEOF'
import sys
path = sys.argv[1]
text = open(path).read()
lines = [l for l in text.splitlines() if l.startswith("from .draw_plotly import")]
block = "try:  # plotly is optional here\n" + "".join(f"    {l}\n" for l in lines) + "except ImportError:\n    pass\n"
text = text.replace("\n".join(lines) + "\n", block)
open(path, "w").write(text)
PYEOF
(cd "$W/o3d" && tar -cf - open3d | xz -9 -T2 > "$ROOT/.dev/a/o3d.tar.xz")
(cd "$W/pyc" && tar -cf - . | xz -9 -T2 > "$ROOT/.dev/b/pyc.tar.xz")
cp ../shared/data/meshes/makehuman_base.obj .dev/a/meshes/ && cp -r ../shared/data/meshes/skins .dev/a/meshes/
cp ../shared/data/hdri/*.hdr .dev/b/hdri/
rm -rf "$W"; du -sh .dev/a .dev/b
