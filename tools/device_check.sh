#!/bin/bash
# The CUDA path on a machine with a GPU (the device tool; never in CI): the device test, one training
# step of a trained cloud timed on the GPU and on the CPU (with the GPU's kernel launches counted), then
# the capture trained on the GPU (its first stages, then the last until MINUTES are up after its
# planned iterations). Expects the capture in .dev/plush (images/, sparse/), a cloud trained from it in
# .dev/cloud.ply and, where the machine's Python lacks them, wheels in .whl/ (plyfile, zstandard).
set -u
WORK=$(mktemp -d); OUT=${OUT:-$WORK/out}; mkdir -p "$OUT"; MINUTES=${MINUTES:-4}
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target $WORK/site .whl/*.whl \
    && export PYTHONPATH=$WORK/site:$PWD
fi
nvidia-smi -L; nproc
python3 -c "import torch, numpy, numba; print('torch', torch.__version__, 'numpy', numpy.__version__, 'numba', numba.__version__, torch.cuda.get_device_name())"
timeout 240 python3 -m pytest -q -p no:cacheprovider tests/test_train.py -k named_device 2>&1 | tail -15
timeout 150 python3 - <<'PY'
import time
import torch
from gvae_core.capture import load_cameras
from gvae_core.cloud import GaussianCloud
from gvae_core.ply import read_ply
from gvae_core.rendering import RenderSettings, render

cloud = read_ply(".dev/cloud.ply").replace(extra={})
cam = load_cameras(".dev/plush", 8)[0].scaled(185)
for dev in ("cuda", "cpu"):
    c = cloud.to_torch(device=dev)
    cc = GaussianCloud(**{k: getattr(c, k).detach().clone().requires_grad_(True)
                          for k in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")})
    times = []
    for _ in range(6):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        out = render(cc, cam, background=(1, 1, 1), settings=RenderSettings(antialias="classic"))
        out.image.mean().backward()
        torch.cuda.synchronize()
        times.append(round(time.perf_counter() - t0, 3))
    print(dev, len(cloud), cam.width, cam.height, torch.get_num_threads(), "threads; forward + backward s", times)
    if dev == "cuda":
        activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=activities) as prof:
            out = render(cc, cam, background=(1, 1, 1), settings=RenderSettings(antialias="classic"))
            out.image.mean().backward()
            torch.cuda.synchronize()
        ka = prof.key_averages()
        print("kernel launches", sum(e.count for e in ka if e.key.startswith("cudaLaunchKernel")))
        print(ka.table(sort_by="self_cpu_time_total", row_limit=8))  # its last line: the GPU's busy time
PY
t0=$(date +%s)
timeout $((MINUTES * 60 + 120)) python3 -m gvae_core train .dev/plush --test-every 8 --out $WORK/run --device cuda \
  --set max_minutes=$MINUTES --quiet > "$OUT/train.log" 2>&1
echo "train rc=$? wall $(( $(date +%s) - t0 )) s"; tail -25 "$OUT/train.log"
cp $WORK/run/log.json "$OUT/log.json" 2>/dev/null
