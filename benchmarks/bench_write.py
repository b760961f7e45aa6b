"""CPU cost of writing one shard's patch arrays with each storage filter (issue 21; docs/benchmarks.md).

    OMP_NUM_THREADS=1 python benchmarks/bench_write.py SHARD.h5
"""
import time, h5py, numpy as np, os, sys, hdf5plugin
from msps_render.dataset.schema import PATCH_CHUNK
from msps_render.dataset.writer import filter_kwargs
src = sys.argv[1]
out = sys.argv[2] if len(sys.argv) > 2 else "/tmp/bench_write.h5"
with h5py.File(src) as h:
    arrs = {k: h["patches"][k][()] for k in h["patches"]}
print({k: (v.shape, v.dtype) for k, v in arrs.items()})
for comp in ["lzf", "zstd", "blosc2-lz4", "none"]:
    ts = []
    for r in range(5):
        t = time.process_time()
        with h5py.File(out, "w") as h:
            g = h.create_group("patches")
            for k, v in arrs.items():
                kw = filter_kwargs(comp)
                g.create_dataset(k, data=v, chunks=(min(PATCH_CHUNK, len(v)),) + v.shape[1:], track_times=False, **kw)
        ts.append(time.process_time() - t)
    print(comp, "median CPU ms per shard", round(1000 * sorted(ts)[2], 1), os.path.getsize(out) // 1024, "KiB")
