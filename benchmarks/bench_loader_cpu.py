"""CPU microseconds per patch of the HDF5 decode alone, per storage filter (issue 21).

Usage: python benchmarks/bench_loader_cpu.py ROOT   (ROOT/<filter>/ corpora, e.g. from bench_loader.py --repack)

CPU time, unlike patches/s, hardly depends on what else runs on the machine; 2e6 / (us per patch)
is the decode ceiling of two fully free cores (a projection, not a measured rate).
"""
import statistics
import sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_loader import decode_rate, _filters, _corpus_bytes
from msps_render.data import PatchDataset
from pathlib import Path
root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path("/tmp/i21-pt")
names = [n for n in ["lzf", "blosc2-lz4", "zstd", "gzip", "none"] if (root / n).is_dir()]
ds = {n: PatchDataset(root / n) for n in names}
for d in ds.values():
    for p, _, _ in d.shards: Path(p).read_bytes()
us = {n: [] for n in names}
for r in range(3):
    for n in names:
        rate, main_us, _ = decode_rate(ds[n], 1)
        us[n].append(main_us)
    print("round", r, {n: round(us[n][-1], 1) for n in names}, flush=True)
for n in names:
    m = statistics.median(us[n]); size = _corpus_bytes(ds[n])
    print(f"| {n} ({_filters(ds[n])}) | {size/1e6:.1f} | {size/len(ds[n]):,.0f} | {m:.1f} | {us['lzf'][0] and statistics.median(us['lzf'])/m:.2f} | {2e6/m:,.0f} |")
